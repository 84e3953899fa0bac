//! Running a scene file end to end, as `cargo xtask simulate` does: the run executor with
//! ParaView frames (`frame_*.vtu` and `series.pvd`), a per-step CSV (`steps.csv`: Newton
//! and linear iterations, residuals, energies, flops, wall time, a tracked vertex) and a
//! `summary.txt`, every file written atomically; with contact, `obstacles.vtu` (where the
//! obstacles start) and, when some move, `obstacles_*.vtu` in `obstacles.pvd` beside the
//! frames.

use std::fmt::Write as _;
use std::io::Write as _;
use std::ops::ControlFlow;
use std::path::{Path, PathBuf};

use deform_mesh::TetMesh;
use deform_mesh::io::{Pvd, Vtu};
use thiserror::Error;

use crate::Integrator;
use crate::observer::Observer;
use crate::report::{IterationReport, StepError, StepReport};
use crate::run::{RunOptions, RunSummary};
use crate::scene::{Scene, SceneError};
use crate::state::State;

/// Why a simulation stopped.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum SimulateError {
    /// The scene does not load or build.
    #[error(transparent)]
    Scene(#[from] SceneError),
    /// A file could not be written.
    #[error("{}: {reason}", path.display())]
    Write {
        /// The file.
        path: PathBuf,
        /// Why.
        reason: String,
    },
    /// Another run is writing into the output folder, or it cannot be created.
    #[error(transparent)]
    Locked(#[from] deform_fs::LockError),
    /// A step failed (the files hold the steps before it).
    #[error("{}: step {step} (t = {t:.4} s): {source}", scene.display())]
    Step {
        /// The scene file.
        scene: PathBuf,
        /// The failed step (1-based, as in `steps.csv`).
        step: usize,
        /// Time before the step.
        t: f64,
        /// Why.
        source: Box<StepError>,
    },
}

/// What a simulation did.
#[derive(Debug, Clone)]
pub struct Simulation {
    /// The results folder.
    pub out: PathBuf,
    /// The run's totals.
    pub run: RunSummary,
    /// The final state.
    pub state: State,
    /// The tracked vertex and its final position.
    pub tracked: (usize, [f64; 3]),
}

/// Runs the scene file `scene_path` for `steps` steps (the scene's own count by default)
/// into `out` (default `target/deform/simulate/<scene name>`), every iteration and step also
/// going to `observer`.
///
/// # Errors
/// [`SimulateError`] naming the scene, the file or the failed step.
pub fn simulate(
    scene_path: &Path,
    steps: Option<usize>,
    out: Option<&Path>,
    observer: &mut dyn Observer,
) -> Result<Simulation, SimulateError> {
    let scene = Scene::load(scene_path)?;
    if steps == Some(0) {
        return Err(SceneError::Invalid {
            path: scene_path.to_path_buf(),
            field: "steps".into(),
            reason: "the number of steps asked for must be at least 1".into(),
        }
        .into());
    }
    let built = scene.build(scene_path)?;
    let (mesh, mut sim, mut state) = (built.mesh, built.integrator, built.state);
    let steps = steps.unwrap_or(scene.steps);
    let out = out.map_or_else(
        || Path::new("target/deform/simulate").join(&scene.name),
        Path::to_path_buf,
    );
    let _lock = deform_fs::lock_folder(&out)?;
    clear_previous_run(&out)?;
    let tracked = scene.tracked_vertex(&mesh);
    // Appended and flushed step by step, so it always matches the frames on disk.
    let csv_path = out.join("steps.csv");
    let mut csv = std::fs::File::create(&csv_path).map_err(|e| write_error(&csv_path, e))?;
    csv.write_all(b"step,t,dt,newton_iterations,linear_iterations,initial_residual,final_residual,elastic_energy,kinetic_energy,flops,seconds,retries,tracked_x,tracked_y,tracked_z,contacts,min_distance,capped_line_searches\n")
        .map_err(|e| write_error(&csv_path, e))?;
    let mut log = StepLog {
        csv: (csv, csv_path),
        masses: sim.assembly().vertex_masses(sim.mass()),
        tracked,
        frames: Frames {
            out: &out,
            mesh: &mesh,
            every: scene.output.every,
            pvd: Pvd::new(out.join("series.pvd")),
            obstacles: MovingObstacles::new(&out, &mesh, &sim),
        },
        error: None,
        user: observer,
    };
    log.frames.write(0, &state)?;
    write_obstacles(&out, &mesh, &sim, state.t)?;
    let run = sim.run(&mut state, &RunOptions::steps(steps), &mut log);
    if let Some(e) = log.error {
        return Err(e);
    }
    let t_before = state.t;
    let run = run.into_result().map_err(|e| SimulateError::Step {
        scene: scene_path.to_path_buf(),
        step: e.step + 1,
        t: t_before,
        source: e.source,
    })?;
    let position = [
        state.x[3 * tracked],
        state.x[3 * tracked + 1],
        state.x[3 * tracked + 2],
    ];
    let text = format!(
        "scene: {}\nmesh: {} vertices, {} tets, {} free DOFs\npolicy: {}\nsteps: {steps} (dt = {} s, t = {:.4} s)\nNewton iterations: {} ({:.2} per step)\nlinear iterations: {}\nwall time: {:.3} s of steps, {:.3} s total\ntracked vertex {tracked}: ({:.6}, {:.6}, {:.6})\n",
        scene.name,
        mesh.num_vertices(),
        mesh.num_tets(),
        sim.dofs().num_free(),
        sim.policy().name(),
        scene.integrator.dt,
        state.t,
        run.newton_iterations,
        run.newton_iterations as f64 / steps.max(1) as f64,
        run.linear_iterations,
        run.step_seconds,
        run.seconds,
        position[0],
        position[1],
        position[2],
    );
    let peak = deform_mesh::memory::peak_rss_bytes().map_or("unknown".to_owned(), |b| {
        format!("{:.1} MB", b as f64 / 1e6)
    });
    let text = format!("{text}peak memory (resident, whole process): {peak}\n");
    deform_fs::write_text(&out.join("summary.txt"), &text).map_err(fs_error)?;
    Ok(Simulation {
        out,
        run,
        state,
        tracked: (tracked, position),
    })
}

/// The obstacles' surfaces in `obstacles.vtu`, to open in ParaView beside the frames (a
/// plane as a square three times the body's size), where they are at the start.
fn write_obstacles(
    out: &Path,
    mesh: &TetMesh,
    sim: &Integrator,
    state_time: f64,
) -> Result<(), SimulateError> {
    let Some(contact) = sim.contact() else {
        return Ok(());
    };
    let path = out.join("obstacles.vtu");
    let (obstacles, meshes) = contact.placed_at(state_time);
    write_surfaces(&path, &obstacles, &meshes, extent(mesh))
}

/// The size of a plane's square: three times the body's.
fn extent(mesh: &TetMesh) -> f64 {
    let (lo, hi) = mesh.bounding_box();
    3.0 * (hi - lo).norm()
}

/// `obstacles` (analytic) and `meshes` as triangles in `path`.
fn write_surfaces(
    path: &Path,
    obstacles: &[deform_contact::Obstacle],
    meshes: &[deform_contact::Surface],
    extent: f64,
) -> Result<(), SimulateError> {
    let (mut x, mut triangles) = (Vec::new(), Vec::new());
    let analytic = obstacles.iter().map(|o| o.surface(extent));
    for (p, t) in analytic.chain(meshes.iter().cloned()) {
        let first = x.len() / 3;
        x.extend(p);
        triangles.extend(t.iter().map(|tri| tri.map(|i| i + first)));
    }
    deform_mesh::io::write_triangles(path, &x, &triangles).map_err(|e| write_error(path, e))
}

/// Moving obstacles in frames of their own (`obstacles_*.vtu`, `obstacles.pvd`) beside the
/// body's, where they are at each frame's time.
struct MovingObstacles {
    contact: deform_contact::ContactModel,
    extent: f64,
    pvd: Pvd,
}

impl MovingObstacles {
    fn new(out: &Path, mesh: &TetMesh, sim: &Integrator) -> Option<Self> {
        let contact = sim.contact().filter(|c| !c.motions().is_empty())?;
        Some(Self {
            contact: contact.clone(),
            extent: extent(mesh),
            pvd: Pvd::new(out.join("obstacles.pvd")),
        })
    }

    fn write(&mut self, out: &Path, step: usize, t: f64) -> Result<(), SimulateError> {
        let (obstacles, meshes) = self.contact.placed_at(t);
        let file = out.join(format!("obstacles_{step:05}.vtu"));
        write_surfaces(&file, &obstacles, &meshes, self.extent)?;
        self.pvd.push(t, &file).map_err(|e| write_error(&file, e))
    }
}

/// Removes what an earlier run left in `out` (frames, series, CSV, summary, and the
/// temporaries of atomic writes a killed run left behind), so the folder only ever holds
/// one run's files.
/// Removes the previous run's frames, series, CSV and summary.
fn clear_previous_run(out: &Path) -> Result<(), SimulateError> {
    deform_fs::clear_previous_run(out, |name, is_dir| {
        let frame = (name.starts_with("frame_") || name.starts_with("obstacles_"))
            && name.ends_with(".vtu");
        let known = [
            "series.pvd",
            "steps.csv",
            "summary.txt",
            "obstacles.vtu",
            "obstacles.pvd",
        ];
        !is_dir && (frame || known.contains(&name))
    })
    .map_err(fs_error)
}

fn write_error(path: &Path, e: impl std::fmt::Display) -> SimulateError {
    SimulateError::Write {
        path: path.to_path_buf(),
        reason: e.to_string(),
    }
}

fn fs_error(e: deform_fs::WriteError) -> SimulateError {
    write_error(&e.path, e.error)
}

/// ParaView frames every `every` steps (none when 0).
struct Frames<'a> {
    out: &'a Path,
    mesh: &'a TetMesh,
    every: usize,
    pvd: Pvd,
    obstacles: Option<MovingObstacles>,
}

impl Frames<'_> {
    fn write(&mut self, step: usize, state: &State) -> Result<(), SimulateError> {
        if self.every == 0 || !step.is_multiple_of(self.every) {
            return Ok(());
        }
        let file = self.out.join(format!("frame_{step:05}.vtu"));
        Vtu::deformed(self.mesh, &state.x)
            .point_vectors("velocity", &state.v)
            .write(&file)
            .map_err(|e| write_error(&file, e))?;
        self.pvd
            .push(state.t, &file)
            .map_err(|e| write_error(&file, e))?;
        match &mut self.obstacles {
            Some(o) => o.write(self.out, step, state.t),
            None => Ok(()),
        }
    }
}

/// Writes `steps.csv` rows and frames step by step, then hands the step to the caller's
/// observer; stops the run when a file cannot be written.
struct StepLog<'a> {
    csv: (std::fs::File, PathBuf),
    masses: Vec<f64>,
    tracked: usize,
    frames: Frames<'a>,
    error: Option<SimulateError>,
    user: &'a mut dyn Observer,
}

impl Observer for StepLog<'_> {
    fn iteration(&mut self, report: &IterationReport) {
        self.user.iteration(report);
    }

    fn step(&mut self, report: &StepReport, state: &State) -> ControlFlow<()> {
        let step = report.step + 1;
        let kinetic: f64 = state
            .v
            .iter()
            .enumerate()
            .map(|(i, v)| 0.5 * self.masses[i / 3] * v * v)
            .sum();
        let tracked = &state.x[3 * self.tracked..3 * self.tracked + 3];
        let mut row = String::new();
        let _ = writeln!(
            row,
            "{step},{:.6},{:e},{},{},{:e},{:e},{:e},{:e},{},{:.6},{},{:.9},{:.9},{:.9},{},{},{}",
            report.t,
            report.dt,
            report.newton_iterations(),
            report.linear_iterations(),
            report.initial_residual,
            report.final_residual,
            report.energy,
            kinetic,
            report.flops(),
            report.seconds,
            report.retries,
            tracked[0],
            tracked[1],
            tracked[2],
            report.contact.map_or(0, |c| c.active),
            report
                .contact
                .map_or(String::new(), |c| format!("{:e}", c.min_distance)),
            report.capped_line_searches(),
        );
        let (file, path) = &mut self.csv;
        if let Err(e) = file.write_all(row.as_bytes()).and_then(|()| file.flush()) {
            self.error = Some(write_error(path, e));
            return ControlFlow::Break(());
        }
        if let Err(e) = self.frames.write(step, state) {
            self.error = Some(e);
            return ControlFlow::Break(());
        }
        self.user.step(report, state)
    }
}

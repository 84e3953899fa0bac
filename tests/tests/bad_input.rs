//! The bad-input corpus: every kind of bad input reported against deform (issue 18), as a
//! small file or RON snippet, run through the entry points a user runs (the mesh readers,
//! `simulate`, `Experiment::load` + `experiment::run`, the `.npy` import). Each case must
//! end in a typed error naming the file and the field, line or element, within a time
//! bound, without a panic and without writing results. The tally (tried / typed error /
//! panic / hang / silently accepted) is printed with `--nocapture`.

use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::Duration;

use deform_integrator::{NoObserver, simulate};
use deform_studies::{Experiment, ExperimentObserver, Stage};

/// A scene that runs; cases replace parts of it.
const SCENE: &str = r#"Scene(
    name: "tiny",
    mesh: Beam(1),
    material: NeoHookean(Young(e: 1e5, nu: 0.4)),
    density: 1000.0,
    constraints: [(select: Plane(point: (0.0, 0.0, 0.0), normal: (-1.0, 0.0, 0.0)))],
    integrator: (dt: 0.01, newton: (rel: 1e-8)),
    steps: 2,
)"#;

/// An experiment that runs on [`SCENE`]; cases replace parts of it.
const EXPERIMENT: &str = r#"Experiment(
    name: "x",
    scene: "scene.ron",
    dataset: (trajectories: 3, steps: 2, seed: 1, split: (0.34, 0.33)),
    task: SelectSolver(candidates: [Direct()]),
)"#;

/// A valid Gmsh 2.2 tet (and a point element).
const MSH: &str = "$MeshFormat\n2.2 0 8\n$EndMeshFormat\n$Nodes\n5\n1 0 0 0\n2 1 0 0\n3 0 1 0\n4 0 0 1\n5 0 0 -1\n$EndNodes\n$Elements\n2\n1 4 2 1 1 1 2 3 4\n2 4 2 1 1 1 3 2 5\n$EndElements\n";

/// What a case feeds and to which entry point.
enum Input {
    /// A mesh file read by `deform_mesh::io::read`: name and content.
    Mesh(&'static str, String),
    /// A TetGen pair: `.node` and `.ele` content, read through the `.ele`.
    Tetgen(String, String),
    /// A scene file run by `simulate` (with an optional step count), beside the files given.
    Scene(String, Option<usize>, Vec<(&'static str, String)>),
    /// An experiment file loaded and run (beside the tiny scene).
    Experiment(String),
    /// A positions `.npy` imported as a trajectory.
    Npy(Vec<u8>),
}

struct Case {
    what: &'static str,
    input: Input,
    /// Every string the error must contain (the file, the field, line or element).
    names: &'static [&'static str],
}

fn scene(from: &str, to: &str) -> String {
    assert!(SCENE.contains(from), "{from}");
    SCENE.replace(from, to)
}

fn experiment(from: &str, to: &str) -> String {
    assert!(EXPERIMENT.contains(from), "{from}");
    EXPERIMENT.replace(from, to)
}

/// A little-endian f64 `.npy` of `shape` filled with `value`.
fn npy(shape: &[usize], value: f64) -> Vec<u8> {
    let dims: Vec<String> = shape.iter().map(|d| format!("{d},")).collect();
    let mut header = format!(
        "{{'descr': '<f8', 'fortran_order': False, 'shape': ({}), }}",
        dims.join(" ")
    );
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend((header.len() as u16).to_le_bytes());
    out.extend(header.as_bytes());
    for _ in 0..shape.iter().product::<usize>() {
        out.extend(value.to_le_bytes());
    }
    out
}

fn corpus() -> Vec<Case> {
    use Input::*;
    let msh = |from: &str, to: &str| {
        assert!(MSH.contains(from), "{from}");
        MSH.replace(from, to)
    };
    let node = "5 3 0 0\n1 0 0 0\n2 1 0 0\n3 0 1 0\n4 0 0 1\n5 0 0 -1\n".to_owned();
    vec![
        Case {
            what: "truncated .msh",
            input: Mesh("a.msh", MSH[..MSH.len() / 2].into()),
            names: &["a.msh:"],
        },
        Case {
            what: "NaN coordinate",
            input: Mesh("a.msh", msh("3 0 1 0", "3 0 nan 0")),
            names: &["a.msh", "file node 3"],
        },
        Case {
            what: "hostile node count",
            input: Mesh("a.msh", msh("$Nodes\n5", "$Nodes\n99999999999")),
            names: &["a.msh:5"],
        },
        Case {
            what: "elements doubled",
            input: Mesh(
                "a.msh",
                msh(
                    "$Elements\n2\n",
                    "$Elements\n4\n3 4 2 1 1 1 2 3 4\n4 4 2 1 1 1 3 2 5\n",
                ),
            ),
            names: &["a.msh", "file elements 1 and 3"],
        },
        Case {
            what: "overlapping tets",
            input: Mesh("a.msh", msh("5 0 0 -1", "5 0.2 0.2 0.5")),
            names: &["a.msh", "file elements 1 and 2", "overlap"],
        },
        Case {
            what: "a hexahedron among the tets",
            input: Mesh(
                "a.msh",
                msh(
                    "$Elements\n2\n",
                    "$Elements\n3\n9 5 2 1 1 1 2 3 4 5 1 2 3\n",
                ),
            ),
            names: &["a.msh:14", "type 5"],
        },
        Case {
            what: "degenerate tet",
            input: Mesh("a.msh", msh("4 0 0 1", "4 1 1 0")),
            names: &["a.msh", "file element 1", "degenerate"],
        },
        Case {
            what: "unknown format",
            input: Mesh("a.stl", "solid".into()),
            names: &["a.stl"],
        },
        Case {
            what: ".ele header undercounts",
            input: Tetgen(node.clone(), "1 4 0\n1 1 2 3 4\n2 1 3 2 5\n".into()),
            names: &["a.ele:3", "1 tetrahedra"],
        },
        Case {
            what: ".ele node out of range",
            input: Tetgen(node.clone(), "1 4 0\n7 1 2 3 9\n".into()),
            names: &["a.ele", "file element 7"],
        },
        Case {
            what: ".node dimension 2",
            input: Tetgen(
                node.replace("5 3 0 0", "5 2 0 0"),
                "1 4 0\n1 1 2 3 4\n".into(),
            ),
            names: &["a.node:1", "dimension"],
        },
        Case {
            what: "scene: steps 0",
            input: Scene(scene("steps: 2", "steps: 0"), None, vec![]),
            names: &["scene.ron", "steps"],
        },
        Case {
            what: "simulate --steps 0",
            input: Scene(SCENE.into(), Some(0), vec![]),
            names: &["scene.ron", "steps"],
        },
        Case {
            what: "scene: path-like name",
            input: Scene(scene("\"tiny\"", "\"../../x\""), None, vec![]),
            names: &["scene.ron", "name"],
        },
        Case {
            what: "scene: negative density",
            input: Scene(scene("1000.0", "-1.0"), None, vec![]),
            names: &["scene.ron", "density"],
        },
        Case {
            what: "scene: Poisson ratio 0.5",
            input: Scene(scene("nu: 0.4", "nu: 0.5"), None, vec![]),
            names: &["scene.ron", "material"],
        },
        Case {
            what: "scene: NaN dt",
            input: Scene(scene("dt: 0.01", "dt: NaN"), None, vec![]),
            names: &["scene.ron", "dt"],
        },
        Case {
            what: "scene: max_retries 1000",
            input: Scene(
                scene("dt: 0.01", "dt: 0.01, max_retries: 1000"),
                None,
                vec![],
            ),
            names: &["scene.ron", "max_retries"],
        },
        Case {
            what: "scene: unknown field",
            input: Scene(scene("steps: 2", "steps: 2, stepz: 3"), None, vec![]),
            names: &["scene.ron", "stepz"],
        },
        Case {
            what: "scene: a mesh too large for any machine",
            input: Scene(scene("Beam(1)", "Beam(560)"), None, vec![]),
            names: &["scene.ron", "mesh", "needs at least"],
        },
        Case {
            what: "scene: missing mesh file",
            input: Scene(scene("Beam(1)", "File(\"gone.msh\")"), None, vec![]),
            names: &["scene.ron", "gone.msh"],
        },
        Case {
            what: "scene: mesh with doubled elements",
            input: Scene(
                scene("Beam(1)", "File(\"twice.msh\")"),
                None,
                vec![(
                    "twice.msh",
                    msh(
                        "$Elements\n2\n",
                        "$Elements\n4\n3 4 2 1 1 1 2 3 4\n4 4 2 1 1 1 3 2 5\n",
                    ),
                )],
            ),
            names: &["scene.ron", "twice.msh", "file elements 1 and 3"],
        },
        Case {
            what: "scene: negative PCG tolerance",
            input: Scene(
                scene(
                    "steps: 2",
                    "steps: 2, policy: Fixed(Pcg(preconditioner: Jacobi, tolerance: (rel: -1.0)))",
                ),
                None,
                vec![],
            ),
            names: &["scene.ron", "policy"],
        },
        Case {
            what: "scene: contact dhat 1e-300 (no default kappa)",
            input: Scene(
                scene(
                    "steps: 2",
                    "steps: 2, contact: Some((obstacles: [Plane(point: (0.0, 0.0, -1.0), normal: (0.0, 0.0, 1.0))], dhat: Some(1e-300)))",
                ),
                None,
                vec![],
            ),
            names: &["scene.ron", "contact.dhat", "1e-300 m", "give kappa"],
        },
        Case {
            what: "scene: contact dhat 1e300 (no default kappa)",
            input: Scene(
                scene(
                    "steps: 2",
                    "steps: 2, contact: Some((obstacles: [Plane(point: (0.0, 0.0, -1.0), normal: (0.0, 0.0, 1.0))], dhat: Some(1e300)))",
                ),
                None,
                vec![],
            ),
            names: &["scene.ron", "contact.dhat", "1e300 m"],
        },
        Case {
            what: "scene: NaN offset of a mesh obstacle",
            input: Scene(
                scene(
                    "steps: 2",
                    "steps: 2, contact: Some((obstacles: [], meshes: [(file: \"ground.obj\", offset: (0.0, NaN, 0.0))]))",
                ),
                None,
                vec![(
                    "ground.obj",
                    "v -1 -1 -1\nv 3 -1 -1\nv -1 3 -1\nf 1 2 3\n".into(),
                )],
            ),
            names: &["scene.ron", "meshes[0].offset", "NaN"],
        },
        Case {
            what: "experiment: no candidates",
            input: Experiment(experiment("[Direct()]", "[]")),
            names: &["bad.ron", "task.candidates"],
        },
        Case {
            what: "experiment: NaN forcing",
            input: Experiment(experiment(
                "[Direct()])",
                "[Direct()], forcing: Some((NaN, 0.9)))",
            )),
            names: &["bad.ron", "task.forcing"],
        },
        Case {
            what: "experiment: NaN factor weight",
            input: Experiment(experiment("[Direct()])", "[Direct()], factor_weight: NaN)")),
            names: &["bad.ron", "task.factor_weight"],
        },
        Case {
            what: "experiment: no neighbours",
            input: Experiment(experiment("[Direct()])", "[Direct()], neighbours: 0)")),
            names: &["bad.ron", "task.neighbours"],
        },
        Case {
            what: "experiment: empty test set",
            input: Experiment(
                experiment("split: (0.34, 0.33)", "split: (0.6, 0.2)")
                    .replace("SelectSolver(candidates: [Direct()])", "FitMaterial()"),
            ),
            names: &["bad.ron", "dataset.split", "use split: (0.667, 0.000)"],
        },
        Case {
            what: "experiment: dataset conditions that do not fit the scene",
            input: Experiment(experiment(
                "split: (0.34, 0.33)",
                "split: (0.34, 0.33), conditions: [(motions: Some([]))]",
            )),
            names: &["bad.ron", "dataset.conditions[0]", "motions"],
        },
        Case {
            what: "experiment: negative noise",
            input: Experiment(experiment(
                "split: (0.34, 0.33)",
                "split: (0.34, 0.33), noise: Some((position: -0.1, velocity: 0.0, seed: 1))",
            )),
            names: &["bad.ron", "dataset.noise"],
        },
        Case {
            what: "experiment: unknown member",
            input: Experiment(experiment(
                "SelectSolver(candidates: [Direct()])",
                "SelectModel(members: [Bogus])",
            )),
            names: &["bad.ron", "Bogus"],
        },
        Case {
            what: "experiment: a parameter tuned twice",
            input: Experiment(experiment(
                "SelectSolver(candidates: [Direct()])",
                "TuneSolver(solver: Pcg(preconditioner: Jacobi), parameters: [Omega, Omega])",
            )),
            names: &["bad.ron", "task.parameters"],
        },
        Case {
            what: "experiment: Jacobi omega 5",
            input: Experiment(experiment(
                "SelectSolver(candidates: [Direct()])",
                "TuneSolver(solver: Jacobi(omega: 5.0))",
            )),
            names: &["bad.ron", "omega"],
        },
        Case {
            what: "experiment: missing scene",
            input: Experiment(experiment("\"scene.ron\"", "\"nowhere.ron\"")),
            names: &["nowhere.ron"],
        },
        Case {
            what: "npy: shape (3, 0, 3)",
            input: Npy(npy(&[3, 0, 3], 0.0)),
            names: &["x.npy"],
        },
        Case {
            what: "npy: NaN positions",
            input: Npy(npy(&[3, 2, 3], f64::NAN)),
            names: &["x.npy"],
        },
        Case {
            what: "npy: two dimensions",
            input: Npy(npy(&[3, 6], 0.0)),
            names: &["x.npy"],
        },
        Case {
            what: "npy: garbage header",
            input: Npy(b"\x93NUMPY\x01\x00\x10\x00{'descr': '<f8'\n".to_vec()),
            names: &["x.npy"],
        },
    ]
}

/// Outcome of one case.
#[derive(Debug, PartialEq)]
enum Outcome {
    /// A typed error with this message.
    Error(String),
    Panic,
    Hang,
    Accepted,
}

/// Experiments run quietly.
struct Quiet;

impl ExperimentObserver for Quiet {
    fn start(&mut self, _: Stage, _: u64) {}
    fn advance(&mut self, _: u64) {}
    fn message(&mut self, _: &str) {}
    fn finish(&mut self) {}
}

/// Runs `input` in `dir` through its entry point; results go to `dir/out`.
fn feed(input: Input, dir: &Path) -> Result<(), String> {
    let out = dir.join("out");
    let write = |name: &str, text: &[u8]| {
        let path = dir.join(name);
        std::fs::write(&path, text).unwrap();
        path
    };
    match input {
        Input::Mesh(name, text) => {
            let path = write(name, text.as_bytes());
            let options = deform_mesh::MeshOptions::default();
            deform_mesh::io::read(&path, &options)
                .map(drop)
                .map_err(|e| e.to_string())
        }
        Input::Tetgen(node, ele) => {
            write("a.node", node.as_bytes());
            let path = write("a.ele", ele.as_bytes());
            let options = deform_mesh::MeshOptions::default();
            deform_mesh::io::read(&path, &options)
                .map(drop)
                .map_err(|e| e.to_string())
        }
        Input::Scene(text, steps, files) => {
            for (name, text) in files {
                write(name, text.as_bytes());
            }
            let path = write("scene.ron", text.as_bytes());
            simulate(&path, steps, Some(&out), &mut NoObserver)
                .map(drop)
                .map_err(|e| e.to_string())
        }
        Input::Experiment(text) => {
            write("scene.ron", SCENE.as_bytes());
            let path = write("bad.ron", text.as_bytes());
            let e = Experiment::load(&path).map_err(|e| e.to_string())?;
            deform_studies::run(&e, Some(&out), &mut Quiet)
                .map(drop)
                .map_err(|e| e.to_string())
        }
        Input::Npy(bytes) => {
            let path = write("x.npy", &bytes);
            deform_learn::import::import_trajectory(
                &path,
                deform_learn::import::Velocities::Derived,
                0.01,
            )
            .map(drop)
            .map_err(|e| e.to_string())
        }
    }
}

/// Runs one case on its own thread, so a panic is caught and a hang is bounded.
fn run(input: Input, dir: PathBuf) -> Outcome {
    let (send, receive) = mpsc::channel();
    std::thread::spawn(move || {
        let outcome = match catch_unwind(AssertUnwindSafe(|| feed(input, &dir))) {
            Ok(Ok(())) => Outcome::Accepted,
            Ok(Err(message)) => Outcome::Error(message),
            Err(_) => Outcome::Panic,
        };
        let _ = send.send(outcome);
    });
    receive
        .recv_timeout(Duration::from_secs(120))
        .unwrap_or(Outcome::Hang)
}

/// Files a failed run left in its results folder (the lock file aside).
fn written(out: &Path) -> Vec<String> {
    let Ok(entries) = std::fs::read_dir(out) else {
        return Vec::new();
    };
    entries
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|name| name != ".deform.lock")
        .collect()
}

#[test]
fn every_bad_input_gets_a_typed_error_naming_it_and_writes_nothing() {
    let cases = corpus();
    let tried = cases.len();
    let (mut errors, mut panics, mut hangs, mut accepted) = (0, 0, 0, 0);
    let mut failures = Vec::new();
    for case in cases {
        let dir = tempfile::tempdir().unwrap();
        let outcome = run(case.input, dir.path().to_owned());
        match &outcome {
            Outcome::Error(message) => {
                errors += 1;
                let missing: Vec<_> = case
                    .names
                    .iter()
                    .filter(|n| !message.contains(*n))
                    .collect();
                if !missing.is_empty() {
                    failures.push(format!(
                        "{}: {message:?} does not name {missing:?}",
                        case.what
                    ));
                }
                let left = written(&dir.path().join("out"));
                if !left.is_empty() {
                    failures.push(format!("{}: wrote {left:?}", case.what));
                }
            }
            Outcome::Panic => panics += 1,
            Outcome::Hang => hangs += 1,
            Outcome::Accepted => accepted += 1,
        }
        if !matches!(outcome, Outcome::Error(_)) {
            failures.push(format!("{}: {outcome:?}", case.what));
        }
    }
    println!(
        "bad-input corpus: {tried} tried, {errors} typed errors, {panics} panics, {hangs} hangs, {accepted} silently accepted"
    );
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

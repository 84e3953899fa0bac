//! The systems of the beam family of `docs/benchmarks.md`, for benchmarks and for exporting to other solvers.

use deform_assembly::{Assembly, DofMap, MaterialField, Tangent};
use deform_materials::{Lame, Model, NeoHookean};
use deform_mesh::TetMesh;
use deform_mesh::generate::BoxGrid;
use sprs::CsMat;

/// The beam of size `n`, its Neo-Hookean material (E = 1e6, nu = 0.4) and the deformed state
/// `x = X + (0.01 x z, 0.005 sin 3x, -0.1 x^2)`.
pub fn beam(n: usize) -> (TetMesh, MaterialField, Vec<f64>) {
    let mesh = BoxGrid::beam(n)
        .build()
        .expect("the benchmark beam is valid");
    let lame = Lame::from_young(1e6, 0.4).expect("valid moduli");
    let material = MaterialField::Uniform(Model::NeoHookean(NeoHookean { lame }));
    let x = mesh
        .rest_positions()
        .iter()
        .flat_map(|p| {
            [
                p.x + 0.01 * p.x * p.z,
                p.y + 0.005 * (3.0 * p.x).sin(),
                p.z - 0.1 * p.x * p.x,
            ]
        })
        .collect();
    (mesh, material, x)
}

/// The Backward-Euler system `K(x) + M / dt^2` (density 1000, dt = 0.01, lumped mass) of the
/// beam of size `n` on its free DOFs (the vertices at x = 0 are clamped).
pub fn beam_system(n: usize) -> CsMat<f64> {
    let (mesh, material, x) = beam(n);
    let mut asm = Assembly::new(&mesh, material).expect("the benchmark assembly is valid");
    let mut k = asm.stiffness_matrix();
    asm.stiffness(&x, Tangent::Exact, &mut k)
        .expect("the benchmark state is admissible");
    let mass = deform_assembly::Mass::lumped(&mesh, 1000.0);
    let dt = 0.01;
    let mut a = asm.stiffness_matrix();
    asm.combine(1.0 / (dt * dt), &mass, 1.0, &k, &mut a)
        .expect("same pattern");
    let clamped: Vec<usize> = (0..mesh.num_vertices())
        .filter(|&v| mesh.rest_positions()[v].x == 0.0)
        .collect();
    let dofs = DofMap::new(mesh.num_vertices(), &clamped).expect("valid vertices");
    let mut reduced = dofs.reduced_matrix(&a).expect("a 3N x 3N matrix");
    dofs.restrict_matrix(&a, &mut reduced)
        .expect("same pattern");
    reduced.matrix
}

/// Rest positions of the free vertices of [`beam_system`], one per 3 rows in row order (for
/// geometric orderings, `LinearSolver::set_coordinates`).
pub fn beam_free_coordinates(n: usize) -> Vec<[f64; 3]> {
    let (mesh, _, _) = beam(n);
    mesh.rest_positions()
        .iter()
        .filter(|p| p.x != 0.0)
        .map(|p| [p.x, p.y, p.z])
        .collect()
}

/// `f`'s result and wall time.
fn timed<T>(f: impl FnOnce() -> T) -> (T, f64) {
    let t = std::time::Instant::now();
    let out = f();
    (out, t.elapsed().as_secs_f64())
}

/// The middle value (the upper one of an even count).
///
/// # Panics
/// If `v` is empty.
pub fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// [`median_time`] after one untimed call that allocates and first touches what `f`
/// uses: a pass of milliseconds would otherwise time page faults.
fn warm_median_time<T>(repeats: usize, mut f: impl FnMut() -> T) -> (T, f64) {
    f();
    median_time(repeats, f)
}

/// Median over `repeats` of `f`'s wall time, and its last result.
fn median_time<T>(repeats: usize, mut f: impl FnMut() -> T) -> (T, f64) {
    let mut times = Vec::new();
    let mut last = None;
    for _ in 0..repeats.max(1) {
        let (out, t) = timed(&mut f);
        last = Some(out);
        times.push(t);
    }
    (last.expect("at least one run"), median(times))
}

/// Which of the assembly's outputs a timing asks for: the Newton loop asks for each of
/// these (the line search for the energy, a converged check for energy and forces).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AssemblyOutputs {
    /// The energy alone.
    Energy,
    /// Energy and forces.
    EnergyForces,
    /// K alone.
    Stiffness,
    /// Energy, forces and K in one pass.
    All,
}

impl AssemblyOutputs {
    /// Every kind, cheapest first.
    pub const ALL: [AssemblyOutputs; 4] = [
        AssemblyOutputs::Energy,
        AssemblyOutputs::EnergyForces,
        AssemblyOutputs::Stiffness,
        AssemblyOutputs::All,
    ];

    /// Its name in reports.
    pub fn name(self) -> &'static str {
        match self {
            AssemblyOutputs::Energy => "energy",
            AssemblyOutputs::EnergyForces => "energy+forces",
            AssemblyOutputs::Stiffness => "K",
            AssemblyOutputs::All => "energy+forces+K",
        }
    }
}

/// Median wall time of one assembly of `outputs` of `material` on the beam of size `n` at
/// its deformed state (in blocks of `block_elements`, or the assembly's default).
///
/// # Errors
/// The assembly's.
pub fn time_assembly(
    n: usize,
    material: MaterialField,
    outputs: AssemblyOutputs,
    block_elements: Option<usize>,
    repeats: usize,
) -> Result<f64, deform_assembly::AssemblyError> {
    let (mesh, _, x) = beam(n);
    let mut asm = Assembly::new(&mesh, material)?;
    if let Some(b) = block_elements {
        asm.set_block_elements(b);
    }
    let mut k = asm.stiffness_matrix();
    let mut f = vec![0.0; x.len()];
    let (energy, forces, stiffness) = match outputs {
        AssemblyOutputs::Energy => (true, false, false),
        AssemblyOutputs::EnergyForces => (true, true, false),
        AssemblyOutputs::Stiffness => (false, false, true),
        AssemblyOutputs::All => (true, true, true),
    };
    let (result, seconds) = warm_median_time(repeats, || {
        let mut e = 0.0;
        asm.evaluate(
            &x,
            deform_assembly::Outputs {
                energy: energy.then_some(&mut e),
                forces: forces.then_some(&mut f[..]),
                stiffness: stiffness.then_some(&mut k),
                tangent: Tangent::Exact,
                ..Default::default()
            },
        )
    });
    result.map(|()| seconds)
}

/// One direct-solver configuration on a system: median phase times and what it produced.
#[derive(Debug, Clone, PartialEq)]
pub struct DirectTiming {
    /// Its name in reports.
    pub name: &'static str,
    /// Median analysis, factorisation and solve times (s).
    pub analyze: f64,
    /// Factorisation.
    pub factorize: f64,
    /// Solve.
    pub solve: f64,
    /// Nonzeros of the factor.
    pub factor_nnz: usize,
    /// `||b - A x|| / ||b||`.
    pub relative_residual: f64,
    /// Refinement steps (mixed precision).
    pub refinement_steps: usize,
}

/// The direct solver on `a x = b`: ordered from the matrix alone (`_graph`, what PARDISO
/// gets) or with the nodes' `coordinates`, on one thread or two tasks, in double or mixed
/// precision; medians of `repeats`.
///
/// # Errors
/// The solver's.
pub fn time_direct(
    a: &CsMat<f64>,
    b: &[f64],
    coordinates: &[[f64; 3]],
    repeats: usize,
) -> Result<Vec<DirectTiming>, deform_solvers::SolverError> {
    use deform_solvers::{Precision, SolverSpec};
    let mut out = Vec::new();
    for (name, parallel, precision, geometry) in [
        ("direct_graph", true, Precision::Double, false),
        ("direct_one_thread", false, Precision::Double, true),
        ("direct", true, Precision::Double, true),
        ("direct_mixed_graph", true, Precision::Mixed, false),
        ("direct_mixed", true, Precision::Mixed, true),
        ("direct_mixed_one_thread", false, Precision::Mixed, true),
    ] {
        let (mut analyze, mut factor, mut solve) = (Vec::new(), Vec::new(), Vec::new());
        let (mut nnz, mut residual, mut steps) = (0, f64::NAN, 0);
        for _ in 0..repeats.max(1) {
            let spec = SolverSpec::Direct {
                ordering: Default::default(),
                indefinite: Default::default(),
                parallel,
                precision,
            };
            let mut s = spec.build()?;
            if geometry {
                s.set_coordinates(Some(coordinates));
            }
            let (r, t) = timed(|| s.analyze(a));
            r?;
            analyze.push(t);
            let (setup, t) = timed(|| s.factorize(a));
            nnz = setup?.factor_nnz;
            factor.push(t);
            let mut x = vec![0.0; b.len()];
            let (stats, t) = timed(|| s.solve(a, b, &mut x));
            let stats = stats?;
            residual = stats.relative_residual();
            steps = stats.iterations;
            solve.push(t);
        }
        out.push(DirectTiming {
            name,
            analyze: median(analyze),
            factorize: median(factor),
            solve: median(solve),
            factor_nnz: nnz,
            relative_residual: residual,
            refinement_steps: steps,
        });
    }
    Ok(out)
}

/// One iterative solver's median timing from a cold start.
#[derive(Debug, Clone)]
pub struct IterativeTiming {
    /// The solver's name in the benchmark.
    pub name: &'static str,
    /// Iterations to the tolerance.
    pub iterations: usize,
    /// Median set-up (preconditioner) seconds.
    pub setup: f64,
    /// Median seconds of set-up and solve together.
    pub seconds: f64,
    /// Seconds of set-up and solve together in each round (every solver ran once per
    /// round, in order, so ratios between solvers are best taken round by round).
    pub rounds: Vec<f64>,
    /// Set-up flops (deterministic; the rates of the three kinds of flops give
    /// [`deform_solvers::WorkWeights`]).
    pub setup_flops: u64,
    /// Solve flops, sweeps included.
    pub solve_flops: u64,
    /// The solve's flops in sequential sweeps.
    pub sweep_flops: u64,
}

/// The iterative solvers `cargo xtask bench solvers` compares, by name: CG and PCG
/// (Jacobi, IC(0), smoothed-aggregation AMG).
pub const ITERATIVE_SOLVERS: [(&str, &str); 6] = [
    (
        "cg_1e-6",
        "Cg(tolerance: (rel: 1e-6, max_iterations: 100000))",
    ),
    (
        "pcg_jacobi_1e-6",
        "Pcg(preconditioner: Jacobi, tolerance: (rel: 1e-6, max_iterations: 100000))",
    ),
    (
        "pcg_jacobi_1e-8",
        "Pcg(preconditioner: Jacobi, tolerance: (rel: 1e-8, max_iterations: 100000))",
    ),
    (
        "pcg_ic0_1e-6",
        "Pcg(preconditioner: Ic0, tolerance: (rel: 1e-6, max_iterations: 100000))",
    ),
    (
        "pcg_amg_1e-6",
        "Pcg(preconditioner: Amg(), tolerance: (rel: 1e-6, max_iterations: 100000))",
    ),
    (
        "pcg_amg_jacobi_1e-6",
        "Pcg(preconditioner: Amg(smoother: Jacobi(sweeps: 1)), tolerance: (rel: 1e-6, max_iterations: 100000))",
    ),
];

/// `solvers` (names and specs, e.g. from [`ITERATIVE_SOLVERS`]) on `a x = b` from a cold
/// start, with the rigid-body modes of `coordinates` for AMG, medians over `repeats` rounds
/// (each runs every solver once).
///
/// # Errors
/// The solver's.
pub fn time_iterative(
    a: &CsMat<f64>,
    b: &[f64],
    coordinates: &[[f64; 3]],
    solvers: &[(&'static str, &str)],
    repeats: usize,
) -> Result<Vec<IterativeTiming>, deform_solvers::SolverError> {
    let specs: Vec<deform_solvers::SolverSpec> = solvers
        .iter()
        .map(|(_, spec)| ron::from_str(spec).expect("a valid spec"))
        .collect();
    // Rounds of one run per solver, so every solver sees the same drift of the machine's
    // speed and the ratios between them hold within a round.
    let mut runs: Vec<Vec<(f64, f64)>> = vec![Vec::new(); specs.len()];
    let mut last = Vec::new();
    for _ in 0..repeats.max(1) {
        last.clear();
        for (spec, times) in specs.iter().zip(&mut runs) {
            let (stats, seconds) = timed(|| {
                let mut s = spec.build()?;
                s.set_coordinates(Some(coordinates));
                let mut x = vec![0.0; b.len()];
                let setup = s.factorize(a)?;
                Ok::<_, deform_solvers::SolverError>((setup, s.solve(a, b, &mut x)?))
            });
            let (setup, solve) = stats?;
            times.push((setup.seconds, seconds));
            last.push((setup, solve));
        }
    }
    Ok(solvers
        .iter()
        .zip(runs)
        .zip(last)
        .map(|((&(name, _), times), (setup, solve))| IterativeTiming {
            name,
            iterations: solve.iterations,
            setup: median(times.iter().map(|t| t.0).collect()),
            seconds: median(times.iter().map(|t| t.1).collect()),
            rounds: times.iter().map(|t| t.1).collect(),
            setup_flops: setup.flops,
            solve_flops: solve.flops,
            sweep_flops: solve.sweep_flops,
        })
        .collect())
}

/// The solver policies `cargo xtask bench step` compares, by name.
pub const STEP_POLICIES: [(&str, &str); 12] = [
    ("direct", "Fixed(Direct())"),
    ("direct_one_thread", "Fixed(Direct(parallel: false))"),
    ("direct_mixed", "Fixed(Direct(precision: Mixed))"),
    // Factorise once (PCG with a fresh factor converges in one iteration), then reuse the
    // stale factor in later Newton iterations and steps.
    (
        "stale_cholesky_pcg",
        "Fixed(Pcg(preconditioner: StaleCholesky(max_age: 20), tolerance: (rel: 1e-8)))",
    ),
    // The same with the factor in single precision.
    (
        "stale_cholesky_pcg_mixed",
        "Fixed(Pcg(preconditioner: StaleCholesky(max_age: 20, precision: Mixed), tolerance: (rel: 1e-8)))",
    ),
    // The hand schedule: refactorise after a solve needing more than 20 iterations.
    (
        "stale_factor_20",
        "StaleFactor(solver: Pcg(preconditioner: StaleCholesky(max_age: 1000), tolerance: (rel: 1e-8)), refactor_above: 20)",
    ),
    (
        "pcg_ic0",
        "Fixed(Pcg(preconditioner: Ic0, tolerance: (rel: 1e-8)))",
    ),
    (
        "eisenstat_walker_ic0",
        "EisenstatWalker(solver: Pcg(preconditioner: Ic0, tolerance: (rel: 1e-8)))",
    ),
    (
        "pcg_jacobi",
        "Fixed(Pcg(preconditioner: Jacobi, tolerance: (rel: 1e-8)))",
    ),
    // Smoothed-aggregation AMG with the rest positions' rigid-body modes: a new hierarchy
    // per Newton iteration, and one hierarchy refreshed with new values for 20 set-ups.
    (
        "pcg_amg",
        "Fixed(Pcg(preconditioner: Amg(), tolerance: (rel: 1e-8)))",
    ),
    (
        "pcg_amg_refresh",
        "Fixed(Pcg(preconditioner: Amg(max_age: 20), tolerance: (rel: 1e-8)))",
    ),
    (
        "amg_rebuild_above_40",
        "StaleFactor(solver: Pcg(preconditioner: Amg(max_age: 1000), tolerance: (rel: 1e-8)), refactor_above: 40)",
    ),
];

/// The clamped beam of size `n` under gravity from rest, as an integrator with `policy`
/// (one of [`STEP_POLICIES`]' texts) and its initial state.
///
/// # Errors
/// A policy text that does not parse or build.
pub fn beam_integrator(
    n: usize,
    policy: &str,
) -> Result<(crate::Integrator, crate::State), crate::PolicyError> {
    beam_integrator_with(n, policy, None)
}

/// [`beam_integrator`] with barrier contact as `contact` says (e.g. a ground under the beam,
/// which its tip reaches as it sags).
///
/// # Errors
/// A policy text that does not parse or build.
///
/// # Panics
/// When `contact` does not build (an invalid obstacle).
pub fn beam_integrator_with(
    n: usize,
    policy: &str,
    contact: Option<crate::ContactSpec>,
) -> Result<(crate::Integrator, crate::State), crate::PolicyError> {
    let (mesh, material, _) = beam(n);
    let clamp: Vec<usize> = (0..mesh.num_vertices())
        .filter(|&v| mesh.rest_positions()[v].x == 0.0)
        .collect();
    let policy = ron::from_str::<crate::PolicySpec>(policy)
        .map_err(|e| crate::PolicyError::Invalid {
            field: "policy",
            reason: e.to_string(),
        })?
        .build()?;
    let mut builder = crate::Integrator::builder(&mesh, material)
        .constraints(vec![crate::Constraint {
            vertices: clamp,
            motion: crate::Motion::Fixed,
        }])
        .policy(policy);
    if let Some(contact) = contact {
        builder = builder.contact(contact);
    }
    let sim = builder.build().expect("the benchmark beam builds");
    let state = sim.rest_state();
    Ok((sim, state))
}

/// A stage whose speed-up with threads `cargo xtask bench scaling` measures: the assembly's
/// outputs, the solvers' kernels and set-ups, and one Backward-Euler step with its parts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ScalingStage {
    /// One assembly of these outputs at the beam's deformed state.
    Assembly(AssemblyOutputs),
    /// `y = A x` with the Backward-Euler system.
    Spmv,
    /// Smoothed-aggregation AMG's set-up (with the rest positions' rigid-body modes).
    AmgSetup,
    /// One PCG iteration preconditioned by an AMG V-cycle.
    AmgIteration,
    /// IC(0)'s factorisation.
    Ic0Setup,
    /// One PCG iteration preconditioned by IC(0) (two triangular sweeps).
    Ic0Iteration,
    /// The sparse Cholesky factorisation (nested dissection by the rest positions), its
    /// symbolic analysis excluded.
    Factorize,
    /// The first step from rest of the clamped beam under gravity with PCG-AMG (a new
    /// hierarchy per Newton iteration), all of it.
    Step,
    /// That step's residuals (assembly of energy, forces and K included).
    StepResidual,
    /// That step's Newton matrices on the free DOFs.
    StepMatrix,
    /// That step's linear solves.
    StepDirection,
    /// That step's line searches.
    StepLineSearch,
    /// The machine's ceiling for passes that only read: a dot product of two vectors of
    /// [`MEMORY_LEN`] doubles (far beyond any cache), in fixed chunks.
    MemoryRead,
    /// The ceiling for passes that write: `c = a + 3 b` over [`MEMORY_LEN`] doubles
    /// (STREAM's triad), what every vector update and product with a vector does.
    MemoryTriad,
}

/// Doubles per vector of the memory ceilings (128 MB each).
pub const MEMORY_LEN: usize = 16 << 20;

impl ScalingStage {
    /// Every stage, in report order.
    pub const ALL: [ScalingStage; 17] = [
        ScalingStage::Assembly(AssemblyOutputs::Energy),
        ScalingStage::Assembly(AssemblyOutputs::EnergyForces),
        ScalingStage::Assembly(AssemblyOutputs::Stiffness),
        ScalingStage::Assembly(AssemblyOutputs::All),
        ScalingStage::Spmv,
        ScalingStage::AmgSetup,
        ScalingStage::AmgIteration,
        ScalingStage::Ic0Setup,
        ScalingStage::Ic0Iteration,
        ScalingStage::Factorize,
        ScalingStage::Step,
        ScalingStage::StepResidual,
        ScalingStage::StepMatrix,
        ScalingStage::StepDirection,
        ScalingStage::StepLineSearch,
        ScalingStage::MemoryRead,
        ScalingStage::MemoryTriad,
    ];

    /// Its name in reports and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            ScalingStage::Assembly(AssemblyOutputs::Energy) => "assembly_energy",
            ScalingStage::Assembly(AssemblyOutputs::EnergyForces) => "assembly_forces",
            ScalingStage::Assembly(AssemblyOutputs::Stiffness) => "assembly_k",
            ScalingStage::Assembly(AssemblyOutputs::All) => "assembly_all",
            ScalingStage::Spmv => "spmv",
            ScalingStage::AmgSetup => "amg_setup",
            ScalingStage::AmgIteration => "amg_iteration",
            ScalingStage::Ic0Setup => "ic0_setup",
            ScalingStage::Ic0Iteration => "ic0_iteration",
            ScalingStage::Factorize => "factorize",
            ScalingStage::Step => "step",
            ScalingStage::StepResidual => "step_residual",
            ScalingStage::StepMatrix => "step_matrix",
            ScalingStage::StepDirection => "step_direction",
            ScalingStage::StepLineSearch => "step_line_search",
            ScalingStage::MemoryRead => "memory_read",
            ScalingStage::MemoryTriad => "memory_triad",
        }
    }

    /// Whether it is the step or one of its parts.
    pub fn is_step(self) -> bool {
        matches!(
            self,
            ScalingStage::Step
                | ScalingStage::StepResidual
                | ScalingStage::StepMatrix
                | ScalingStage::StepDirection
                | ScalingStage::StepLineSearch
        )
    }

    /// The stage of this name.
    pub fn from_name(name: &str) -> Option<ScalingStage> {
        Self::ALL.into_iter().find(|s| s.name() == name)
    }
}

/// Why a scaling measurement failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum BenchError {
    /// The assembly failed.
    #[error("assembly: {0}")]
    Assembly(#[from] deform_assembly::AssemblyError),
    /// A solver failed.
    #[error("solver: {0}")]
    Solver(#[from] deform_solvers::SolverError),
    /// The step failed.
    #[error("step: {0}")]
    Step(#[from] crate::StepError),
    /// The step's policy did not build.
    #[error("policy: {0}")]
    Policy(#[from] crate::PolicyError),
}

/// The beam's system, its free vertices' rest positions and a right-hand side.
type BeamSystem = (CsMat<f64>, Vec<[f64; 3]>, Vec<f64>);

/// Median wall times (s) of `stages` on the beam of size `n` over `repeats`, in the current
/// rayon pool (run it inside `ThreadPool::install` to choose the thread count). Each set-up
/// (system, integrator) is made once, outside the timings.
///
/// # Errors
/// The first stage that fails.
pub fn time_stages(
    n: usize,
    stages: &[ScalingStage],
    repeats: usize,
) -> Result<Vec<(ScalingStage, f64)>, BenchError> {
    let mut out = Vec::new();
    let mut system: Option<BeamSystem> = None;
    let mut step: Option<Vec<(crate::StageSeconds, f64)>> = None;
    let mut iterative: Vec<IterativeTiming> = Vec::new();
    for &stage in stages {
        let solver_stage = matches!(
            stage,
            ScalingStage::Spmv
                | ScalingStage::AmgSetup
                | ScalingStage::AmgIteration
                | ScalingStage::Ic0Setup
                | ScalingStage::Ic0Iteration
                | ScalingStage::Factorize
        );
        if solver_stage && system.is_none() {
            let a = beam_system(n);
            let b = (0..a.rows())
                .map(|i| ((i % 7) as f64 - 3.0) * 1e-3)
                .collect();
            system = Some((a, beam_free_coordinates(n), b));
        }
        let system = || system.as_ref().expect("made above");
        let seconds = match stage {
            ScalingStage::Assembly(outputs) => {
                let (_, material, _) = beam(n);
                time_assembly(n, material, outputs, None, repeats)?
            }
            ScalingStage::Spmv => {
                let (a, _, b) = system();
                let mut y = vec![0.0; b.len()];
                warm_median_time(repeats, || {
                    deform_solvers::LinearOperator::apply(a, b, &mut y)
                })
                .1
            }
            ScalingStage::AmgSetup
            | ScalingStage::AmgIteration
            | ScalingStage::Ic0Setup
            | ScalingStage::Ic0Iteration => {
                let amg = matches!(stage, ScalingStage::AmgSetup | ScalingStage::AmgIteration);
                let name = if amg { "pcg_amg_1e-6" } else { "pcg_ic0_1e-6" };
                // Set-up and iteration come from one measurement of the solver.
                let index = match iterative.iter().position(|t| t.name == name) {
                    Some(i) => i,
                    None => {
                        let (a, coordinates, b) = system();
                        let solver = named(&ITERATIVE_SOLVERS, name);
                        iterative.extend(time_iterative(a, b, coordinates, solver, repeats)?);
                        iterative.len() - 1
                    }
                };
                let setup = matches!(stage, ScalingStage::AmgSetup | ScalingStage::Ic0Setup);
                per_iteration(&iterative[index], setup)
            }
            ScalingStage::Factorize => {
                let (a, coordinates, _) = system();
                let spec = deform_solvers::SolverSpec::Direct {
                    ordering: Default::default(),
                    indefinite: Default::default(),
                    parallel: true,
                    precision: Default::default(),
                };
                let mut s = spec.build()?;
                s.set_coordinates(Some(coordinates));
                s.analyze(a)?;
                let (result, seconds) = median_time(repeats, || s.factorize(a));
                result?;
                seconds
            }
            ScalingStage::MemoryRead | ScalingStage::MemoryTriad => {
                memory_pass(stage == ScalingStage::MemoryTriad, repeats)
            }
            _ => {
                if step.is_none() {
                    step = Some(time_steps(n, repeats)?);
                }
                let runs = step.as_ref().expect("just measured");
                let part = |f: fn(&(crate::StageSeconds, f64)) -> f64| {
                    median(runs.iter().map(f).collect())
                };
                match stage {
                    ScalingStage::StepResidual => part(|(s, _)| s.residual),
                    ScalingStage::StepMatrix => part(|(s, _)| s.matrix),
                    ScalingStage::StepDirection => part(|(s, _)| s.direction),
                    ScalingStage::StepLineSearch => part(|(s, _)| s.line_search),
                    _ => part(|(_, whole)| *whole),
                }
            }
        };
        out.push((stage, seconds));
    }
    Ok(out)
}

/// The median seconds of one pass over [`MEMORY_LEN`]-long vectors, in the current pool:
/// a triad (two read, one written) or a dot product (two read, the solvers' fixed-chunk
/// `dot`). At least five repeats, as a pass takes milliseconds. The triad zips its chunks
/// rather than indexing them ([`deform_solvers::vector::for_each_entry`] with `a[i]`,
/// `b[i]` took twice as long on one thread: bounds checks, no vector instructions), so that
/// it streams memory and nothing else.
fn memory_pass(triad: bool, repeats: usize) -> f64 {
    use rayon::prelude::*;
    const CHUNK: usize = deform_solvers::vector::VECTOR_CHUNK;
    let a = vec![1.0; MEMORY_LEN];
    let b = vec![2.0; MEMORY_LEN];
    let mut c = vec![0.0; MEMORY_LEN];
    let repeats = repeats.max(5);
    if triad {
        let pass = || {
            let chunks = c.par_chunks_mut(CHUNK);
            chunks
                .zip(a.par_chunks(CHUNK).zip(b.par_chunks(CHUNK)))
                .for_each(|(c, (a, b))| {
                    for ((c, a), b) in c.iter_mut().zip(a).zip(b) {
                        *c = a + 3.0 * b;
                    }
                })
        };
        warm_median_time(repeats, pass).1
    } else {
        let (sum, seconds) = warm_median_time(repeats, || deform_solvers::vector::dot(&a, &b));
        assert_eq!(
            sum,
            2.0 * MEMORY_LEN as f64,
            "the dot product of ones and twos"
        );
        seconds
    }
}

/// The entry of `all` called `name`, as a one-entry slice.
fn named<'a>(
    all: &'a [(&'static str, &'static str)],
    name: &str,
) -> &'a [(&'static str, &'static str)] {
    let i = all
        .iter()
        .position(|(n, _)| *n == name)
        .expect("a listed name");
    &all[i..=i]
}

/// The set-up's median seconds, or the solve's per iteration.
fn per_iteration(t: &IterativeTiming, setup: bool) -> f64 {
    if setup {
        t.setup
    } else {
        (t.seconds - t.setup) / t.iterations.max(1) as f64
    }
}

/// `repeats` first steps of the beam from rest with PCG-AMG, each on a restarted integrator
/// (so each builds its hierarchies anew), after one untimed step that allocates and first
/// touches the integrator's buffers: their stages' seconds summed over the Newton
/// iterations, and the whole step's.
fn time_steps(n: usize, repeats: usize) -> Result<Vec<(crate::StageSeconds, f64)>, BenchError> {
    let (mut sim, rest) = beam_integrator(n, named(&STEP_POLICIES, "pcg_amg")[0].1)?;
    sim.step(&mut rest.clone())?;
    let mut out = Vec::new();
    for _ in 0..repeats.max(1) {
        sim.restart();
        let mut state = rest.clone();
        let report = sim.step(&mut state)?;
        let mut sum = crate::StageSeconds::default();
        for i in &report.iterations {
            sum.residual += i.stages.residual;
            sum.matrix += i.stages.matrix;
            sum.direction += i.stages.direction;
            sum.line_search += i.stages.line_search;
        }
        out.push((sum, report.seconds));
    }
    Ok(out)
}

/// The serial fraction `f` of Amdahl's law, `T(p) = T(1) (f + (1 - f) / p)`, fitted by least
/// squares in `T(p) / T(1)` to `(threads, seconds)` pairs that include one thread; `None`
/// without a one-thread time or another count to compare it with. Clamped to `[0, 1]`.
pub fn serial_fraction(times: &[(usize, f64)]) -> Option<f64> {
    let t1 = times.iter().find(|(p, _)| *p == 1)?.1;
    let (mut num, mut den) = (0.0, 0.0);
    for &(p, t) in times.iter().filter(|(p, _)| *p > 1) {
        let inv = 1.0 / p as f64;
        num += (t / t1 - inv) * (1.0 - inv);
        den += (1.0 - inv).powi(2);
    }
    (den > 0.0).then(|| (num / den).clamp(0.0, 1.0))
}

/// The speed-up on `threads` that Amdahl's law predicts for serial fraction `f`.
pub fn amdahl_speedup(f: f64, threads: usize) -> f64 {
    1.0 / (f + (1.0 - f) / threads as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn amdahl_fits_recover_the_serial_fraction_they_were_made_with() {
        for f in [0.0, 0.05, 0.2, 1.0] {
            let times: Vec<(usize, f64)> = [1, 2, 4, 16]
                .iter()
                .map(|&p| (p, 3.0 / amdahl_speedup(f, p)))
                .collect();
            let fitted = serial_fraction(&times).unwrap();
            assert!((fitted - f).abs() < 1e-12, "{f}: {fitted}");
        }
        // Two threads: f from the one speed-up (1.85x gives f = 0.081).
        let f = serial_fraction(&[(1, 1.0), (2, 1.0 / 1.85)]).unwrap();
        assert!((amdahl_speedup(f, 2) - 1.85).abs() < 1e-12);
        assert!((f - (2.0 / 1.85 - 1.0)).abs() < 1e-12);
        assert_eq!(serial_fraction(&[(2, 1.0), (4, 0.5)]), None);
        assert_eq!(serial_fraction(&[(1, 1.0)]), None);
    }

    #[test]
    fn every_stage_is_timed_on_the_smallest_beam() {
        let times = time_stages(1, &ScalingStage::ALL, 1).unwrap();
        assert_eq!(times.len(), ScalingStage::ALL.len());
        for (stage, t) in times {
            assert!(t.is_finite() && t >= 0.0, "{}: {t}", stage.name());
            assert_eq!(ScalingStage::from_name(stage.name()), Some(stage));
        }
    }
}

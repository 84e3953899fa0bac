//! The systems of `shared/BENCHMARKS.md`, for benchmarks and for exporting to other solvers.

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

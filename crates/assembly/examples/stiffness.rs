//! Assemble the stiffness matrix of a gmsh mesh at a deformed state and check it.
//!
//! `cargo run --release -p deform-assembly --example stiffness -- assets/meshes/bracket.msh`

use deform_assembly::{Assembly, MaterialField, Tangent};
use deform_materials::MaterialSpec;
use deform_mesh::MeshOptions;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let path = std::env::args()
        .nth(1)
        .unwrap_or_else(|| "assets/meshes/bracket.msh".into());
    let mesh = deform_mesh::io::read(path.as_ref(), &MeshOptions::default())?;
    let model = ron::from_str::<MaterialSpec>("NeoHookean(Young(e: 2e11, nu: 0.3))")?.build()?;
    let mut asm = Assembly::new(&mesh, MaterialField::Uniform(model))?;
    // Stretch by 1 % along x.
    let x: Vec<f64> = mesh
        .rest_positions()
        .iter()
        .flat_map(|p| [1.01 * p.x, p.y, p.z])
        .collect();
    let mut k = asm.stiffness_matrix();
    let start = std::time::Instant::now();
    asm.stiffness(&x, Tangent::Exact, &mut k)?;
    let elapsed = start.elapsed();
    let mut f = vec![0.0; x.len()];
    asm.forces(&x, &mut f)?;
    let net: f64 = (0..3)
        .map(|c| f.iter().skip(c).step_by(3).sum::<f64>().abs())
        .sum();
    println!(
        "{path}: {} vertices, {} tets",
        mesh.num_vertices(),
        mesh.num_tets()
    );
    println!(
        "K: {} x {}, {} nonzeros, assembled in {:.2} ms",
        k.rows(),
        k.cols(),
        k.nnz(),
        1e3 * elapsed.as_secs_f64()
    );
    println!(
        "elastic energy {:.6e} J, |sum of forces| = {net:.2e} N",
        asm.energy(&x)?
    );
    Ok(())
}

//! Read a mesh file (or generate a beam), print its statistics, pick the clamped side and
//! write a ParaView frame of a sagging shape.
//!
//! `cargo run -p deform-mesh --example inspect -- assets/meshes/bracket.msh`

use std::path::PathBuf;

use deform_mesh::generate::BoxGrid;
use deform_mesh::io::{self, Vtu};
use deform_mesh::quality::rest_quality;
use deform_mesh::select::Selector;
use deform_mesh::{MeshOptions, TetMesh};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mesh: TetMesh = match std::env::args().nth(1) {
        Some(path) => io::read(&PathBuf::from(path), &MeshOptions::default())?,
        None => BoxGrid::beam(4).build()?,
    };
    let q = rest_quality(&mesh);
    println!(
        "{} vertices, {} tets, volume {:.6e}",
        mesh.num_vertices(),
        mesh.num_tets(),
        q.total_volume
    );
    println!(
        "dihedral angles {:.1}..{:.1} deg, max aspect ratio {:.2}",
        q.min_dihedral_deg, q.max_dihedral_deg, q.max_aspect_ratio
    );
    let (lo, _) = mesh.bounding_box();
    let clamp = Selector::Plane {
        point: lo.into(),
        normal: [-1.0, 0.0, 0.0],
    }
    .select(&mesh)?;
    println!("{} vertices on the side x = {:.3}", clamp.len(), lo.x);
    // A made-up sag u_z = -0.1 (x - x0)^2, written with its displacement and volume ratio.
    let x: Vec<f64> = mesh
        .rest_positions()
        .iter()
        .flat_map(|p| [p.x, p.y, p.z - 0.1 * (p.x - lo.x).powi(2)])
        .collect();
    let out = std::env::temp_dir().join("deform_inspect.vtu");
    Vtu::deformed(&mesh, &x).write(&out)?;
    println!("wrote {}", out.display());
    Ok(())
}

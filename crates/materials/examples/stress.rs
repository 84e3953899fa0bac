//! Evaluate every model's stress and stiffness under a uniaxial stretch: the Piola stress
//! `P_xx` and the smallest eigenvalue of the tangent, plain and projected.
//!
//! `cargo run -p deform-materials --example stress`

use deform_materials::{Material, MaterialSpec};
use nalgebra::{Matrix3, SymmetricEigen, Vector3};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let specs = [
        "LinearElastic(Young(e: 1e6, nu: 0.4))",
        "CorotatedLinear(moduli: Young(e: 1e6, nu: 0.4))",
        "FixedCorotated(Young(e: 1e6, nu: 0.4))",
        "StVenantKirchhoff(Young(e: 1e6, nu: 0.4))",
        "NeoHookean(Young(e: 1e6, nu: 0.4))",
        "StableNeoHookean(Young(e: 1e6, nu: 0.4))",
    ];
    println!(
        "{:<56} {:>8} {:>14} {:>14} {:>14}",
        "model", "stretch", "P_xx [Pa]", "min eig", "min eig proj"
    );
    for text in specs {
        let model = ron::from_str::<MaterialSpec>(text)?.build()?;
        for s in [0.5, 0.9, 1.0, 1.1, 2.0] {
            let f = Matrix3::from_diagonal(&Vector3::new(s, 1.0, 1.0));
            let min = |m: deform_materials::Matrix9| SymmetricEigen::new(m).eigenvalues.min();
            println!(
                "{text:<56} {s:>8.2} {:>14.4e} {:>14.4e} {:>14.4e}",
                model.first_piola(&f)[(0, 0)],
                min(model.dp_df(&f)),
                min(model.dp_df_projected(&f))
            );
        }
    }
    Ok(())
}

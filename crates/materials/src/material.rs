//! The `Material` trait: an energy density and its exact derivatives.

use nalgebra::{Matrix3, SMatrix, SVector, SymmetricEigen};

use crate::MaterialError;

/// A 9x9 tangent `dP/dF` in the `vec` ordering of [`vec9`].
pub type Matrix9 = SMatrix<f64, 9, 9>;
/// A flattened 3x3 matrix, see [`vec9`].
pub type Vector9 = SVector<f64, 9>;

/// Column-major flattening: `vec(F)[3 j + i] = F[(i, j)]` (nalgebra's storage order).
/// Tangents use it on both sides: `dp_df[(3 j + i, 3 l + k)] = dP_ij / dF_kl`.
pub fn vec9(m: &Matrix3<f64>) -> Vector9 {
    Vector9::from_column_slice(m.as_slice())
}

/// Inverse of [`vec9`].
pub fn mat3(v: &Vector9) -> Matrix3<f64> {
    Matrix3::from_column_slice(v.as_slice())
}

/// A hyperelastic energy density `Psi(F)` per unit rest volume, with its exact derivatives.
///
/// `P = dPsi/dF` (first Piola-Kirchhoff stress), `dP(F; dF)` its differential and
/// `dp_df` the full 9x9 tangent. Implementations are pure functions of `F`, allocate
/// nothing, and are `Send + Sync`.
///
/// **Domain.** A model may be undefined for some `F` (Neo-Hookean at `det F <= 0`):
/// there `admissible` is false, `psi` is `+inf` (so a line search rejects the state), and
/// `first_piola` / `dp` / `dp_df` are not meaningful. Callers check [`Material::check`]
/// (assembly does, per element, and reports the element), never relying on NaN.
///
/// **Parameter split.** Every model is linear in its parameters: `Psi = sum_k c_k Psi_k(F)`
/// with coefficients `c` ([`Material::coefficients`]) and terms `Psi_k`
/// ([`Material::term_psi`] etc.). For the single models, `c = (mu, lambda)`; for an
/// [`crate::Ensemble`], `c = (w_m mu_m, w_m lambda_m)` over its members. The same split
/// holds for `P` and `dP/dF`, so gradients with respect to parameters are exact and cheap.
pub trait Material: Send + Sync {
    /// A short name, for errors and reports.
    fn name(&self) -> &'static str;

    /// Energy density; `+inf` where not admissible.
    fn psi(&self, f: &Matrix3<f64>) -> f64;

    /// First Piola-Kirchhoff stress `P = dPsi/dF`.
    fn first_piola(&self, f: &Matrix3<f64>) -> Matrix3<f64>;

    /// The tangent `dP/dF` as a 9x9 matrix in [`vec9`] ordering.
    fn dp_df(&self, f: &Matrix3<f64>) -> Matrix9;

    /// The differential `dP = dP/dF : dF`.
    fn dp(&self, f: &Matrix3<f64>, df: &Matrix3<f64>) -> Matrix3<f64> {
        mat3(&(self.dp_df(f) * vec9(df)))
    }

    /// The tangent with its negative eigenvalues clamped to zero: the nearest positive
    /// semi-definite matrix. Equal to [`Material::dp_df`] where that is already PSD.
    fn dp_df_projected(&self, f: &Matrix3<f64>) -> Matrix9 {
        project_psd(&self.dp_df(f))
    }

    /// `P` and the (optionally projected) tangent together, sharing work where the model can.
    fn first_piola_and_tangent(&self, f: &Matrix3<f64>, project: bool) -> (Matrix3<f64>, Matrix9) {
        let t = if project {
            self.dp_df_projected(f)
        } else {
            self.dp_df(f)
        };
        (self.first_piola(f), t)
    }

    /// Whether `F` is in the model's domain.
    fn admissible(&self, _f: &Matrix3<f64>) -> bool {
        true
    }

    /// [`Material::admissible`] as a typed error.
    ///
    /// # Errors
    /// [`MaterialError::NotAdmissible`] with `det F`.
    fn check(&self, f: &Matrix3<f64>) -> Result<(), MaterialError> {
        if self.admissible(f) {
            Ok(())
        } else {
            Err(MaterialError::NotAdmissible {
                model: self.name(),
                det: f.determinant(),
            })
        }
    }

    /// Number of terms of the parameter split.
    fn num_terms(&self) -> usize;

    /// The coefficients `c_k` of the split (length [`Material::num_terms`]).
    fn coefficients(&self, out: &mut [f64]);

    /// Term `k` of the energy.
    fn term_psi(&self, k: usize, f: &Matrix3<f64>) -> f64;

    /// Term `k` of `P`.
    fn term_first_piola(&self, k: usize, f: &Matrix3<f64>) -> Matrix3<f64>;

    /// Term `k` of `dP/dF`.
    fn term_dp_df(&self, k: usize, f: &Matrix3<f64>) -> Matrix9;
}

/// Projects a symmetric 9x9 matrix onto the PSD cone by clamping eigenvalues at zero
/// (numerical eigen-decomposition; the isotropic models use their analytic eigensystems).
pub fn project_psd(m: &Matrix9) -> Matrix9 {
    let sym = (m + m.transpose()) * 0.5;
    let eig = SymmetricEigen::new(sym);
    if eig.eigenvalues.iter().all(|&l| l >= 0.0) {
        return sym;
    }
    let mut out = Matrix9::zeros();
    for (k, &l) in eig.eigenvalues.iter().enumerate() {
        if l > 0.0 {
            let q = eig.eigenvectors.column(k);
            out.ger(l, &q, &q, 1.0);
        }
    }
    out
}

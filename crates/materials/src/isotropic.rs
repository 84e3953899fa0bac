//! Isotropic energies as functions of signed singular values, and their analytic
//! eigensystems (Smith, de Goes, Kim 2019, "Analytic eigensystems for isotropic distortion
//! energies"; Teran et al. 2005 for the 2x2 blocks).
//!
//! With the rotation-fixed SVD `F = U diag(s) V^T` (`U`, `V` proper rotations, only `s[2]`
//! may be negative, which encodes inversion), an isotropic `Psi(F) = Psi(s)` has
//! `P = U diag(g) V^T` with `g = dPsi/ds`, and `dP/dF` has nine eigenmatrices:
//! three scaling modes `U diag(q) V^T` (from the 3x3 Hessian `H = d2Psi/ds2`) and, for each
//! pair `(i, j)`, a flip `U (e_i e_j^T + e_j e_i^T) V^T / sqrt 2` with eigenvalue
//! `a = (g_i - g_j) / (s_i - s_j)` and a twist `U (e_i e_j^T - e_j e_i^T) V^T / sqrt 2` with
//! `b = (g_i + g_j) / (s_i + s_j)`. Each model gives `a` and `b` in closed form, so repeated
//! singular values need no special case; projection to PSD clamps `H`'s eigenvalues and
//! `a`, `b` at zero.

use nalgebra::{Matrix3, Vector3};

use crate::material::Matrix9;
pub(crate) use crate::svd3::SignedSvd;
use crate::svd3::sym_eigen;

/// The three index pairs `(i, j)` and the remaining index `k`.
pub(crate) const PAIRS: [(usize, usize, usize); 3] = [(0, 1, 2), (0, 2, 1), (1, 2, 0)];

/// An isotropic energy in terms of signed singular values.
pub(crate) trait Isotropic {
    /// `Psi(s)`.
    fn psi_s(&self, s: &Vector3<f64>) -> f64;
    /// `dPsi/ds`.
    fn grad_s(&self, s: &Vector3<f64>) -> Vector3<f64>;
    /// `d2Psi/ds2`.
    fn hess_s(&self, s: &Vector3<f64>) -> Matrix3<f64>;
    /// `(a, b)`, the flip and twist eigenvalues of pair `(i, j)`; `k` is the third index.
    fn pair(&self, s: &Vector3<f64>, i: usize, j: usize, k: usize) -> (f64, f64);
}

/// Denominator guard for `b = (g_i + g_j) / (s_i + s_j)` in models where it has no closed
/// form (the corotated energies): the energy's Hessian is unbounded there, we cap it.
pub(crate) fn guard(x: f64) -> f64 {
    const EPS: f64 = 1e-6;
    if x.abs() < EPS { EPS.copysign(x) } else { x }
}

pub(crate) fn first_piola(m: &impl Isotropic, svd: &SignedSvd) -> Matrix3<f64> {
    svd.u * Matrix3::from_diagonal(&m.grad_s(&svd.s)) * svd.v.transpose()
}

/// Full tangent from the eigensystem; with `project`, negative eigenvalues are clamped.
///
/// Written as `A D A^T`: the columns of `A` are the orthonormal modes `vec(u_i v_i^T)` and
/// the flips and twists, `D` is `H` on the first three and diagonal on the rest, so the
/// 9x9 costs one pass of 81 nine-long multiply-adds over fixed arrays.
pub(crate) fn tangent(m: &impl Isotropic, svd: &SignedSvd, project: bool) -> Matrix9 {
    let mut h = m.hess_s(&svd.s);
    if project && !positive_definite(&h) {
        let (l, q) = sym_eigen(&h);
        h = q * Matrix3::from_diagonal(&l.map(|x| x.max(0.0))) * q.transpose();
    }
    // modes[k][r]: row r of column k of A; uv[i][j] = vec(u_i v_j^T).
    let mut uv = [[[0.0; 9]; 3]; 3];
    for (i, row) in uv.iter_mut().enumerate() {
        for (j, mode) in row.iter_mut().enumerate() {
            for c in 0..3 {
                for r in 0..3 {
                    mode[3 * c + r] = svd.u[(r, i)] * svd.v[(c, j)];
                }
            }
        }
    }
    let mut modes = [[0.0; 9]; 9];
    let mut weights = [0.0; 9];
    for k in 0..3 {
        modes[k] = uv[k][k];
    }
    let half = std::f64::consts::FRAC_1_SQRT_2;
    for (n, (i, j, k)) in PAIRS.into_iter().enumerate() {
        let (mut a, mut b) = m.pair(&svd.s, i, j, k);
        if project {
            a = a.max(0.0);
            b = b.max(0.0);
        }
        weights[3 + n] = a;
        weights[6 + n] = b;
        for r in 0..9 {
            modes[3 + n][r] = (uv[i][j][r] + uv[j][i][r]) * half;
            modes[6 + n][r] = (uv[i][j][r] - uv[j][i][r]) * half;
        }
    }
    // (A D)[r][k], then column r of the symmetric result is sum_k (A D)[r][k] A[:, k].
    let mut out = Matrix9::zeros();
    for r in 0..9 {
        let mut ad = [0.0; 9];
        for k in 0..3 {
            ad[k] = (0..3).map(|l| modes[l][r] * h[(l, k)]).sum();
        }
        for k in 3..9 {
            ad[k] = modes[k][r] * weights[k];
        }
        let mut col = [0.0; 9];
        for (k, mode) in modes.iter().enumerate() {
            for (c, m) in col.iter_mut().zip(mode) {
                *c += ad[k] * m;
            }
        }
        out.column_mut(r).copy_from_slice(&col);
    }
    out
}

/// Sylvester's criterion: the leading minors of the symmetric `h` are all positive, so
/// projection would clamp nothing (the common case, spared the eigen-decomposition).
fn positive_definite(h: &Matrix3<f64>) -> bool {
    let m2 = h[(0, 0)] * h[(1, 1)] - h[(0, 1)] * h[(1, 0)];
    h[(0, 0)] > 0.0 && m2 > 0.0 && h.determinant() > 0.0
}

/// `dP = dP/dF : dF` without forming the 9x9 tangent: rotate `dF` into the singular frame,
/// apply the diagonal Hessian and the 2x2 pair blocks, rotate back.
pub(crate) fn dp(m: &impl Isotropic, svd: &SignedSvd, df: &Matrix3<f64>) -> Matrix3<f64> {
    let dfh = svd.u.transpose() * df * svd.v;
    let h = m.hess_s(&svd.s);
    let diag = h * Vector3::new(dfh[(0, 0)], dfh[(1, 1)], dfh[(2, 2)]);
    let mut dph = Matrix3::from_diagonal(&diag);
    for (i, j, k) in PAIRS {
        let (a, b) = m.pair(&svd.s, i, j, k);
        let (p, q) = ((a + b) / 2.0, (a - b) / 2.0);
        dph[(i, j)] = p * dfh[(i, j)] + q * dfh[(j, i)];
        dph[(j, i)] = q * dfh[(i, j)] + p * dfh[(j, i)];
    }
    svd.u * dph * svd.v.transpose()
}

/// `J / s_i`, the product of the other two singular values, without division.
pub(crate) fn cofactor(s: &Vector3<f64>) -> Vector3<f64> {
    Vector3::new(s[1] * s[2], s[0] * s[2], s[0] * s[1])
}

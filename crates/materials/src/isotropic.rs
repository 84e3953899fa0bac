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

use nalgebra::{Matrix3, SymmetricEigen, Vector3};

use crate::material::{Matrix9, Vector9};

/// Rotation-fixed SVD: `f = u * diag(s) * v^T` with `det u = det v = 1`.
#[derive(Debug, Clone, Copy)]
pub(crate) struct SignedSvd {
    pub u: Matrix3<f64>,
    pub s: Vector3<f64>,
    pub v: Matrix3<f64>,
}

impl SignedSvd {
    pub fn new(f: &Matrix3<f64>) -> Self {
        let svd = f.svd(true, true);
        let mut u = svd.u.unwrap_or_else(Matrix3::identity);
        let mut v = svd.v_t.map_or_else(Matrix3::identity, |vt| vt.transpose());
        let mut s = svd.singular_values;
        // nalgebra sorts singular values in decreasing order; flip the smallest one's sign.
        let k = s.imin();
        if u.determinant() < 0.0 {
            u.column_mut(k).neg_mut();
            s[k] = -s[k];
        }
        if v.determinant() < 0.0 {
            v.column_mut(k).neg_mut();
            s[k] = -s[k];
        }
        Self { u, s, v }
    }

    /// The closest rotation `R = U V^T` (polar decomposition `F = R S`).
    pub fn rotation(&self) -> Matrix3<f64> {
        self.u * self.v.transpose()
    }

    /// `vec(u_i v_j^T)`.
    fn mode(&self, i: usize, j: usize) -> Vector9 {
        let mut out = Vector9::zeros();
        for c in 0..3 {
            for r in 0..3 {
                out[3 * c + r] = self.u[(r, i)] * self.v[(c, j)];
            }
        }
        out
    }
}

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
pub(crate) fn tangent(m: &impl Isotropic, svd: &SignedSvd, project: bool) -> Matrix9 {
    let mut out = Matrix9::zeros();
    let d = [svd.mode(0, 0), svd.mode(1, 1), svd.mode(2, 2)];
    let h = m.hess_s(&svd.s);
    if project {
        let eig = SymmetricEigen::new(h);
        for (k, &l) in eig.eigenvalues.iter().enumerate() {
            if l > 0.0 {
                let q = eig.eigenvectors.column(k);
                let mode = d[0] * q[0] + d[1] * q[1] + d[2] * q[2];
                out.ger(l, &mode, &mode, 1.0);
            }
        }
    } else {
        for i in 0..3 {
            for j in 0..3 {
                out.ger(h[(i, j)], &d[i], &d[j], 1.0);
            }
        }
    }
    let half = std::f64::consts::FRAC_1_SQRT_2;
    for (i, j, k) in PAIRS {
        let (mut a, mut b) = m.pair(&svd.s, i, j, k);
        if project {
            a = a.max(0.0);
            b = b.max(0.0);
        }
        let (mij, mji) = (svd.mode(i, j), svd.mode(j, i));
        let flip = (mij + mji) * half;
        let twist = (mij - mji) * half;
        out.ger(a, &flip, &flip, 1.0);
        out.ger(b, &twist, &twist, 1.0);
    }
    out
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

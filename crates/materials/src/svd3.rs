//! Dedicated 3x3 symmetric eigen-decomposition and rotation-fixed SVD.
//!
//! nalgebra's general routines (Householder tridiagonalisation, then implicit QR) took about
//! 0.4 us per 3x3 decomposition, most of an SPD-projected tangent's cost. Here: cyclic
//! Jacobi with exact rotations on the symmetric matrix, and for the SVD the scheme of
//! McAdams et al. 2011 ("Computing the singular value decomposition of 3x3 matrices with
//! minimal branching and elementary floating point operations"): `V` from the eigenvectors
//! of `F^T F`, then a Givens QR of `F V` gives `U` and the singular values on the diagonal
//! of `R`, so `U` stays orthogonal even where singular values repeat or vanish, and the
//! sign of `det F` lands on the last singular value by construction.

use nalgebra::{Matrix3, Vector3};

/// Jacobi sweeps at most; a 3x3 converges in 3-5 (quadratically), this only bounds NaN input.
const MAX_SWEEPS: usize = 12;

/// The eigen-decomposition of a symmetric `a` (only its upper triangle is read):
/// `a = q diag(l) q^T` with `q` a proper rotation (`det q = 1`); `l` is unsorted.
pub(crate) fn sym_eigen(a: &Matrix3<f64>) -> (Vector3<f64>, Matrix3<f64>) {
    let mut d = [a[(0, 0)], a[(1, 1)], a[(2, 2)]];
    // off[k] is the entry of the pair that does not contain k: (1,2), (0,2), (0,1).
    let mut off = [a[(1, 2)], a[(0, 2)], a[(0, 1)]];
    let mut q = Matrix3::identity();
    for _ in 0..MAX_SWEEPS {
        let off2 = off[0] * off[0] + off[1] * off[1] + off[2] * off[2];
        let diag2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
        // Below this the off-diagonal changes no eigenvalue by more than rounding.
        if !(off2 > f64::EPSILON * f64::EPSILON * diag2) {
            break;
        }
        rotate(&mut d, &mut off, &mut q, 0, 1);
        rotate(&mut d, &mut off, &mut q, 0, 2);
        rotate(&mut d, &mut off, &mut q, 1, 2);
    }
    (Vector3::new(d[0], d[1], d[2]), q)
}

/// One Jacobi rotation in the plane `(p, r)`, `p < r`, zeroing that entry (Golub and Van
/// Loan's symmetric Schur decomposition): `a <- J^T a J`, `q <- q J`.
#[inline(always)]
fn rotate(d: &mut [f64; 3], off: &mut [f64; 3], q: &mut Matrix3<f64>, p: usize, r: usize) {
    let k = 3 - p - r;
    let apr = off[k];
    if apr == 0.0 {
        return;
    }
    // tan(theta) = t solves t^2 + 2 t x / y - 1 = 0; the smaller root, written so that the
    // dependent chain is sqrt, sqrt, div (a rotation's latency is the sweep's).
    let (x, y) = (d[r] - d[p], 2.0 * apr);
    let (c, s, t) = if y * y < 1e-16 * x * x {
        // Small angle (every rotation of the last sweep): t = y / 2x to rounding, c = 1.
        let t = y / (2.0 * x);
        (1.0, t, t)
    } else {
        let w = x + (x * x + y * y).sqrt().copysign(x);
        let inv = 1.0 / (w * w + y * y).sqrt();
        let c = w.abs() * inv;
        let s = (y * inv).copysign(y * w);
        (c, s, y / w)
    };
    d[p] -= t * apr;
    d[r] += t * apr;
    off[k] = 0.0;
    // Entry (k, p) is off[r], entry (k, r) is off[p].
    let (akp, akr) = (off[r], off[p]);
    off[r] = c * akp - s * akr;
    off[p] = s * akp + c * akr;
    for i in 0..3 {
        let (qp, qr) = (q[(i, p)], q[(i, r)]);
        q[(i, p)] = c * qp - s * qr;
        q[(i, r)] = s * qp + c * qr;
    }
}

/// Rotation-fixed SVD: `f = u diag(s) v^T` with `det u = det v = 1`; `|s|` in decreasing
/// order and only `s[2]` negative, exactly when `det f < 0` (an inverted element).
#[derive(Debug, Clone, Copy)]
pub(crate) struct SignedSvd {
    pub u: Matrix3<f64>,
    pub s: Vector3<f64>,
    pub v: Matrix3<f64>,
}

impl SignedSvd {
    pub fn new(f: &Matrix3<f64>) -> Self {
        // Scaled to entries of at most 1, so that F^T F neither overflows nor underflows.
        let scale = f.amax();
        if !(scale > 0.0) {
            let s = Vector3::repeat(scale);
            return Self {
                u: Matrix3::identity(),
                s,
                v: Matrix3::identity(),
            };
        }
        let f = f / scale;
        let (l, q) = sym_eigen(&(f.transpose() * f));
        let v = sorted_descending(&l, &q);
        let mut r = f * v;
        let mut u = Matrix3::identity();
        givens(&mut r, &mut u, 0, 1, 0);
        givens(&mut r, &mut u, 0, 2, 0);
        givens(&mut r, &mut u, 1, 2, 1);
        Self {
            u,
            s: Vector3::new(r[(0, 0)], r[(1, 1)], r[(2, 2)]) * scale,
            v,
        }
    }

    /// The closest rotation `R = U V^T` (polar decomposition `F = R S`).
    pub fn rotation(&self) -> Matrix3<f64> {
        self.u * self.v.transpose()
    }
}

/// `q`'s columns ordered by decreasing `l`, one negated after an odd permutation so that the
/// determinant stays 1.
fn sorted_descending(l: &Vector3<f64>, q: &Matrix3<f64>) -> Matrix3<f64> {
    let mut order = [0usize, 1, 2];
    let mut odd = false;
    for (i, j) in [(0, 1), (1, 2), (0, 1)] {
        if l[order[i]] < l[order[j]] {
            order.swap(i, j);
            odd = !odd;
        }
    }
    let mut v =
        Matrix3::from_columns(&[q.column(order[0]), q.column(order[1]), q.column(order[2])]);
    if odd {
        v.column_mut(2).neg_mut();
    }
    v
}

/// A Givens rotation of rows `i` and `j` of `r` that zeroes `r[(j, col)]` and leaves
/// `r[(i, col)] >= 0`; `u` accumulates its transpose so that `u r` is unchanged.
#[inline(always)]
fn givens(r: &mut Matrix3<f64>, u: &mut Matrix3<f64>, i: usize, j: usize, col: usize) {
    let (x, y) = (r[(i, col)], r[(j, col)]);
    let h = (x * x + y * y).sqrt();
    if h == 0.0 {
        return;
    }
    let (c, s) = (x / h, y / h);
    for k in 0..3 {
        let (ri, rj) = (r[(i, k)], r[(j, k)]);
        r[(i, k)] = c * ri + s * rj;
        r[(j, k)] = c * rj - s * ri;
        let (ui, uj) = (u[(k, i)], u[(k, j)]);
        u[(k, i)] = c * ui + s * uj;
        u[(k, j)] = c * uj - s * ui;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Rotation3;
    use proptest::prelude::*;

    fn check_svd(f: &Matrix3<f64>) {
        let svd = SignedSvd::new(f);
        // The largest entry, not the norm: squares underflow at the extreme scales.
        let scale = (3.0 * f.amax()).max(f64::MIN_POSITIVE);
        let back = svd.u * Matrix3::from_diagonal(&svd.s) * svd.v.transpose();
        assert!((back - f).norm() <= 1e-13 * scale, "{f} -> {back}");
        for m in [svd.u, svd.v] {
            assert!((m.transpose() * m - Matrix3::identity()).norm() < 1e-13);
            assert!((m.determinant() - 1.0).abs() < 1e-13);
        }
        let s = svd.s;
        assert!(s[0] >= 0.0 && s[1] >= 0.0, "{s}");
        let tol = 1e-13 * scale;
        assert!(s[0] + tol >= s[1] && s[1] + tol >= s[2].abs(), "{s}");
        if f.determinant() < -1e-12 * scale.powi(3) {
            assert!(s[2] < 0.0, "{s} for det {}", f.determinant());
        }
        // nalgebra's SVD, on a scaled copy: it under- and overflows at the extreme scales.
        let reference = (f / scale).svd(false, false).singular_values * scale;
        let mut ours = [s[0], s[1], s[2].abs()];
        ours.sort_by(|a, b| b.total_cmp(a));
        for (a, b) in ours.iter().zip(reference.iter()) {
            assert!(
                (a - b).abs() <= 1e-13 * scale,
                "{s:e} against {reference:e}"
            );
        }
    }

    #[test]
    fn special_matrices_decompose() {
        let r = Rotation3::from_euler_angles(0.3, -1.2, 2.0).into_inner();
        let flip = Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, -1.0));
        let cases = [
            Matrix3::identity(),
            Matrix3::zeros(),
            r,
            r * flip,
            -Matrix3::identity(),
            r * Matrix3::from_diagonal(&Vector3::new(2.0, 2.0, 0.5)),
            r * Matrix3::from_diagonal(&Vector3::new(1.0, 1e-9, 0.0)),
            Matrix3::from_diagonal(&Vector3::new(0.0, 3.0, 0.0)),
            Matrix3::new(1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0),
            r * 1e-200,
            r * 1e120,
        ];
        for f in &cases {
            check_svd(f);
        }
    }

    #[test]
    fn eigen_reconstructs_symmetric_matrices() {
        let a = Matrix3::new(4.0, 1.0, -2.0, 1.0, 3.0, 0.5, -2.0, 0.5, 1.0);
        let (l, q) = sym_eigen(&a);
        assert!((q * Matrix3::from_diagonal(&l) * q.transpose() - a).norm() < 1e-14 * a.norm());
        assert!((q.determinant() - 1.0).abs() < 1e-14);
        let (l, q) = sym_eigen(&Matrix3::from_diagonal_element(2.0));
        assert_eq!((l, q), (Vector3::repeat(2.0), Matrix3::identity()));
    }

    proptest! {
        #[test]
        fn random_matrices_decompose(
            e in proptest::collection::vec(-2.0f64..2.0, 9),
            rank in 1usize..4,
            angles in proptest::array::uniform3(-3.0f64..3.0),
        ) {
            // Full-rank entries, and products that drop the rank or repeat a singular value.
            let f = Matrix3::from_column_slice(&e);
            check_svd(&f);
            let r = Rotation3::from_euler_angles(angles[0], angles[1], angles[2]).into_inner();
            let mut s = Vector3::new(e[0].abs() + 0.1, e[0].abs() + 0.1, e[1]);
            for k in rank..3 {
                s[k] = 0.0;
            }
            check_svd(&(r * Matrix3::from_diagonal(&s) * f.transpose()));
            check_svd(&(r * Matrix3::from_diagonal(&s)));
        }

        #[test]
        fn random_symmetric_matrices_decompose(e in proptest::collection::vec(-2.0f64..2.0, 6)) {
            let a = Matrix3::new(e[0], e[1], e[2], e[1], e[3], e[4], e[2], e[4], e[5]);
            let (l, q) = sym_eigen(&a);
            let back = q * Matrix3::from_diagonal(&l) * q.transpose();
            prop_assert!((back - a).norm() <= 1e-14 * a.norm().max(1.0));
            prop_assert!((q.transpose() * q - Matrix3::identity()).norm() < 1e-14);
            prop_assert!((q.determinant() - 1.0).abs() < 1e-14);
        }
    }
}

//! Element kernels: the 12x12 element stiffness as ten 3x3 blocks from a 9x9 tangent.

use deform_materials::Matrix9;
use nalgebra::{Matrix3, Vector3};

/// The upper-triangle local pairs `(a, b)`, `a <= b`, in storage order.
#[cfg(test)]
pub(crate) const UPPER: [(usize, usize); 10] = [
    (0, 0),
    (0, 1),
    (0, 2),
    (0, 3),
    (1, 1),
    (1, 2),
    (1, 3),
    (2, 2),
    (2, 3),
    (3, 3),
];

/// Index in [`UPPER`] of the pair `(a, b)` and whether the stored block must be transposed.
pub(crate) const fn upper_slot(a: usize, b: usize) -> (usize, bool) {
    let (lo, hi, t) = if a <= b { (a, b, false) } else { (b, a, true) };
    // Row offsets of the packed upper triangle of a 4x4 matrix.
    let start = [0, 4, 7, 9][lo];
    (start + hi - lo, t)
}

/// `K_ab = w sum_{j,l} C[r + 3j, s + 3l] g_a[j] g_b[l]` for the ten upper pairs.
///
/// With `C_rs[j][l] = C[r + 3j, s + 3l]` and `G = [g_1 g_2 g_3]`, the pairs among vertices
/// 1..3 are `K_ab[r][s] = (G^T C_rs G)[a][b]`: six 3x3 triple products for `r <= s` (major
/// symmetry gives `C_sr = C_rs^T`), 324 multiply-adds instead of the 900 of contracting
/// each block separately. Vertex 0's blocks follow from `g_0 = -(g_1 + g_2 + g_3)`.
#[inline]
pub(crate) fn stiffness_blocks(
    c: &Matrix9,
    g: &[Vector3<f64>; 4],
    w: f64,
    out: &mut [Matrix3<f64>; 10],
) {
    let gm = Matrix3::from_columns(&[g[1], g[2], g[3]]) * w.sqrt();
    let gt = gm.transpose();
    // k[a][b] for a, b in 0..3 (vertices 1..3), a <= b stored.
    let mut k = [[Matrix3::<f64>::zeros(); 3]; 3];
    for r in 0..3 {
        for s in r..3 {
            let crs = Matrix3::from_fn(|j, l| c[(r + 3 * j, s + 3 * l)]);
            let h = gt * crs * gm;
            for a in 0..3 {
                for b in a..3 {
                    k[a][b][(r, s)] = h[(a, b)];
                    k[a][b][(s, r)] = h[(b, a)];
                }
            }
        }
    }
    let [[k11, k12, k13], [_, k22, k23], [_, _, k33]] = k;
    // K_0b = -(K_1b + K_2b + K_3b); K_00 = -(K_01 + K_02 + K_03).
    let k01 = -(k11 + k12.transpose() + k13.transpose());
    let k02 = -(k12 + k22 + k23.transpose());
    let k03 = -(k13 + k23 + k33);
    let k00 = -(k01 + k02 + k03);
    // Diagonal blocks are symmetric in exact arithmetic; make them so in floating point, so
    // the assembled K is exactly symmetric (off-diagonal blocks are stored once and
    // transposed on the gather).
    let sym = |k: Matrix3<f64>| (k + k.transpose()) * 0.5;
    *out = [
        sym(k00),
        k01,
        k02,
        k03,
        sym(k11),
        k12,
        k13,
        sym(k22),
        k23,
        sym(k33),
    ];
}

/// `s P g_a` for the four corners, with `g_0 = -(g_1 + g_2 + g_3)`: element forces
/// (`s = -W`, `P` the stress), force differentials (`P = dP`) and term forces.
#[inline]
pub(crate) fn corner_products(
    p: &Matrix3<f64>,
    g: &[Vector3<f64>; 4],
    s: f64,
) -> [Vector3<f64>; 4] {
    let f1 = s * (p * g[1]);
    let f2 = s * (p * g[2]);
    let f3 = s * (p * g[3]);
    [-(f1 + f2 + f3), f1, f2, f3]
}

/// The element's displacement gradient `dF = sum_a dx_a g_a^T`.
#[inline]
pub(crate) fn gradient(dx: &[Vector3<f64>; 4], g: &[Vector3<f64>; 4]) -> Matrix3<f64> {
    // sum over a of dx_a g_a^T with g_0 = -(g_1 + g_2 + g_3): sum_{a>0} (dx_a - dx_0) g_a^T.
    (dx[1] - dx[0]) * g[1].transpose()
        + (dx[2] - dx[0]) * g[2].transpose()
        + (dx[3] - dx[0]) * g[3].transpose()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn upper_slots_match_the_table() {
        for (u, &(a, b)) in UPPER.iter().enumerate() {
            assert_eq!(upper_slot(a, b), (u, false));
            if a != b {
                assert_eq!(upper_slot(b, a), (u, true));
            }
        }
    }
}

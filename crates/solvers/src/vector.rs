//! Vector passes for long vectors that give the same bits on any number of threads: dot
//! products are partial sums over fixed chunks of entries added in chunk order, and
//! element-wise passes run in fixed chunks (each entry computed alone). Below a length
//! they run on the calling thread with the same arithmetic. The solvers' iterations and
//! the integrator's residuals and merit function use them.

use rayon::prelude::*;

/// Entries per partial sum of dot products and per task of vector updates.
pub const VECTOR_CHUNK: usize = 8192;
/// Below this length vector operations run on the calling thread (same arithmetic).
pub const PARALLEL_LEN: usize = 4 * VECTOR_CHUNK;

/// `sqrt(x . x)`.
pub fn norm(x: &[f64]) -> f64 {
    dot(x, x).sqrt()
}

/// `x . y` as partial sums over fixed chunks of `VECTOR_CHUNK` entries, added in chunk
/// order: the same arithmetic whether the chunks run in parallel or not, so the result does
/// not depend on the thread count.
///
/// # Panics
/// If the lengths differ.
pub fn dot(x: &[f64], y: &[f64]) -> f64 {
    assert_eq!(x.len(), y.len(), "dot of vectors of different lengths");
    let partial = |(a, b): (&[f64], &[f64])| a.iter().zip(b).map(|(p, q)| p * q).sum::<f64>();
    if x.len() < PARALLEL_LEN {
        x.chunks(VECTOR_CHUNK)
            .zip(y.chunks(VECTOR_CHUNK))
            .map(partial)
            .sum()
    } else {
        let parts: Vec<f64> = x
            .par_chunks(VECTOR_CHUNK)
            .zip(y.par_chunks(VECTOR_CHUNK))
            .map(partial)
            .collect();
        parts.iter().sum()
    }
}

/// The conjugate-gradient update `x += alpha p`, `r -= alpha q` in one pass, returning the
/// new `|r|` with the chunked sums of [`norm`] (so the same bits as calling it after).
///
/// # Panics
/// If the lengths differ.
pub fn update_and_norm(x: &mut [f64], r: &mut [f64], alpha: f64, p: &[f64], q: &[f64]) -> f64 {
    let n = x.len();
    assert!(
        r.len() == n && p.len() == n && q.len() == n,
        "lengths differ"
    );
    let chunk = |(c, (xs, rs)): (usize, (&mut [f64], &mut [f64]))| {
        let start = c * VECTOR_CHUNK;
        for (k, (xi, ri)) in xs.iter_mut().zip(rs.iter_mut()).enumerate() {
            *xi += alpha * p[start + k];
            *ri -= alpha * q[start + k];
        }
        rs.iter().map(|v| v * v).sum::<f64>()
    };
    let squares: f64 = if x.len() < PARALLEL_LEN {
        let parts = x.chunks_mut(VECTOR_CHUNK).zip(r.chunks_mut(VECTOR_CHUNK));
        parts.enumerate().map(chunk).sum()
    } else {
        let parts = x
            .par_chunks_mut(VECTOR_CHUNK)
            .zip(r.par_chunks_mut(VECTOR_CHUNK));
        let partial: Vec<f64> = parts.enumerate().map(chunk).collect();
        partial.iter().sum()
    };
    squares.sqrt()
}

/// Applies `f(i, &mut y[i])` to every entry, in parallel chunks for long vectors.
pub fn for_each_entry(y: &mut [f64], f: impl Fn(usize, &mut f64) + Sync + Send) {
    let chunk = |(c, ys): (usize, &mut [f64])| {
        for (k, v) in ys.iter_mut().enumerate() {
            f(c * VECTOR_CHUNK + k, v);
        }
    };
    if y.len() < PARALLEL_LEN {
        y.chunks_mut(VECTOR_CHUNK).enumerate().for_each(chunk);
    } else {
        y.par_chunks_mut(VECTOR_CHUNK).enumerate().for_each(chunk);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn on_threads<T: Send>(threads: usize, f: impl FnOnce() -> T + Send) -> T {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build();
        pool.unwrap().install(f)
    }

    /// Long enough for the parallel path, with a ragged last chunk; values of mixed
    /// magnitude so that the order of the additions shows in the bits.
    fn vector(n: usize, seed: u64) -> Vec<f64> {
        (0..n as u64)
            .map(|i| {
                let h = (i ^ seed).wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 11;
                (h as f64 / (1u64 << 53) as f64 - 0.5) * 10f64.powi((i % 7) as i32 - 3)
            })
            .collect()
    }

    #[test]
    fn passes_give_the_same_bits_on_any_thread_count_and_match_plain_arithmetic() {
        for n in [1000, 5 * PARALLEL_LEN + 17] {
            let (x, y) = (vector(n, 1), vector(n, 2));
            let d1 = on_threads(1, || dot(&x, &y));
            let d3 = on_threads(3, || dot(&x, &y));
            assert_eq!(d1.to_bits(), d3.to_bits(), "{n}");
            let plain: f64 = x.iter().zip(&y).map(|(a, b)| a * b).sum();
            let size = x.iter().map(|a| a * a).sum::<f64>().sqrt()
                * y.iter().map(|b| b * b).sum::<f64>().sqrt();
            assert!((d1 - plain).abs() <= 1e-12 * size, "{n}: {d1} {plain}");
            // The fused update is the two updates and the norm after them, bit for bit.
            let (p, q) = (vector(n, 3), vector(n, 4));
            let fused = |threads| {
                on_threads(threads, || {
                    let (mut a, mut r) = (x.clone(), y.clone());
                    let rn = update_and_norm(&mut a, &mut r, 0.3, &p, &q);
                    (a, r, rn)
                })
            };
            let (a, r, rn) = fused(1);
            assert_eq!(fused(2).2.to_bits(), rn.to_bits());
            let (mut a2, mut r2) = (x.clone(), y.clone());
            for_each_entry(&mut a2, |i, v| *v += 0.3 * p[i]);
            for_each_entry(&mut r2, |i, v| *v -= 0.3 * q[i]);
            assert_eq!(a, a2);
            assert_eq!(r, r2);
            assert_eq!(norm(&r2).to_bits(), rn.to_bits());
        }
    }
}

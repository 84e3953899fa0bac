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

/// Applies `f(&mut y[i], a[i])` to every entry, in parallel chunks for long vectors: the
/// zipped form of [`for_each_entry`], without index arithmetic or bounds checks in the
/// loop, so it vectorises and runs as fast as a plain loop on one thread.
///
/// # Panics
/// If the lengths differ.
pub fn update_from(y: &mut [f64], a: &[f64], f: impl Fn(&mut f64, f64) + Sync + Send) {
    assert_eq!(y.len(), a.len(), "lengths differ");
    let chunk = |(ys, as_): (&mut [f64], &[f64])| {
        ys.iter_mut().zip(as_).for_each(|(v, &x)| f(v, x));
    };
    if y.len() < PARALLEL_LEN {
        y.chunks_mut(VECTOR_CHUNK)
            .zip(a.chunks(VECTOR_CHUNK))
            .for_each(chunk);
    } else {
        y.par_chunks_mut(VECTOR_CHUNK)
            .zip(a.par_chunks(VECTOR_CHUNK))
            .for_each(chunk);
    }
}

/// Applies `f(&mut y[i], a[i], b[i])` to every entry, as [`update_from`] with two inputs.
///
/// # Panics
/// If the lengths differ.
pub fn update_from2(
    y: &mut [f64],
    a: &[f64],
    b: &[f64],
    f: impl Fn(&mut f64, f64, f64) + Sync + Send,
) {
    assert!(y.len() == a.len() && y.len() == b.len(), "lengths differ");
    let chunk = |(ys, (as_, bs)): (&mut [f64], (&[f64], &[f64]))| {
        for ((v, &x), &z) in ys.iter_mut().zip(as_).zip(bs) {
            f(v, x, z);
        }
    };
    if y.len() < PARALLEL_LEN {
        let inputs = a.chunks(VECTOR_CHUNK).zip(b.chunks(VECTOR_CHUNK));
        y.chunks_mut(VECTOR_CHUNK).zip(inputs).for_each(chunk);
    } else {
        let inputs = a.par_chunks(VECTOR_CHUNK).zip(b.par_chunks(VECTOR_CHUNK));
        y.par_chunks_mut(VECTOR_CHUNK).zip(inputs).for_each(chunk);
    }
}

/// Applies `f(&mut y[i], a[i], b[i], c[i])` to every entry, as [`update_from`] with three
/// inputs.
///
/// # Panics
/// If the lengths differ.
pub fn update_from3(
    y: &mut [f64],
    [a, b, c]: [&[f64]; 3],
    f: impl Fn(&mut f64, f64, f64, f64) + Sync + Send,
) {
    let n = y.len();
    assert!(
        a.len() == n && b.len() == n && c.len() == n,
        "lengths differ"
    );
    type Inputs<'a> = ((&'a [f64], &'a [f64]), &'a [f64]);
    let chunk = |(ys, ((as_, bs), cs)): (&mut [f64], Inputs<'_>)| {
        for (((v, &x), &z), &w) in ys.iter_mut().zip(as_).zip(bs).zip(cs) {
            f(v, x, z, w);
        }
    };
    if n < PARALLEL_LEN {
        let inputs = a.chunks(VECTOR_CHUNK).zip(b.chunks(VECTOR_CHUNK));
        let inputs = inputs.zip(c.chunks(VECTOR_CHUNK));
        y.chunks_mut(VECTOR_CHUNK).zip(inputs).for_each(chunk);
    } else {
        let inputs = a.par_chunks(VECTOR_CHUNK).zip(b.par_chunks(VECTOR_CHUNK));
        let inputs = inputs.zip(c.par_chunks(VECTOR_CHUNK));
        y.par_chunks_mut(VECTOR_CHUNK).zip(inputs).for_each(chunk);
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

    /// The zipped passes compute each entry as the indexed one does: the same bits, on any
    /// number of threads.
    #[test]
    fn zipped_passes_give_the_indexed_bits_on_any_thread_count() {
        for n in [1000, 5 * PARALLEL_LEN + 17] {
            let (y, a, b) = (vector(n, 5), vector(n, 6), vector(n, 7));
            let mut indexed = y.clone();
            for_each_entry(&mut indexed, |i, v| *v = a[i] + 0.7 * b[i] - *v);
            for threads in [1, 2, 3] {
                let zipped = on_threads(threads, || {
                    let mut z = y.clone();
                    update_from2(&mut z, &a, &b, |v, x, w| *v = x + 0.7 * w - *v);
                    z
                });
                assert_eq!(zipped, indexed, "{n} on {threads}");
                let one = on_threads(threads, || {
                    let mut z = y.clone();
                    update_from(&mut z, &a, |v, x| *v += 0.3 * x);
                    z
                });
                let mut plain = y.clone();
                plain.iter_mut().zip(&a).for_each(|(v, x)| *v += 0.3 * x);
                assert_eq!(one, plain, "{n} on {threads}");
                let three = on_threads(threads, || {
                    let mut z = y.clone();
                    update_from3(&mut z, [&a, &b, &y], |v, x, w, u| *v -= 0.1 * (x + w + u));
                    z
                });
                let mut plain = y.clone();
                for_each_entry(&mut plain, |i, v| *v -= 0.1 * (a[i] + b[i] + y[i]));
                assert_eq!(three, plain, "{n} on {threads}");
            }
        }
    }
}

//! Distances between the primitives of triangle surfaces: a point and a triangle, two edges.
//!
//! The distance between two closed primitives is the distance between two of their
//! sub-primitives, found by which region the closest points lie in (IPC's distance types):
//! point-point, point-edge (point to line), point-plane, or line-line. Each is a smooth
//! function of the pair's points, which is what the barrier's derivatives differentiate.

use nalgebra::Vector3;

use crate::jet::{Jet, JetPoint, cross, dot, sub};

/// Which sub-primitives realise a pair's distance, by index into the pair's four points
/// (`[p, a, b, c]` for a point and a triangle; `[a0, a1, b0, b1]` for two edges).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Form {
    /// Between points `i` and `j`.
    PointPoint(usize, usize),
    /// From point `i` to the line through `j` and `k`.
    PointLine(usize, usize, usize),
    /// From point `i` to the plane through `j`, `k` and `l`.
    PointPlane(usize, usize, usize, usize),
    /// Between the line through `i`, `j` and the line through `k`, `l`.
    LineLine(usize, usize, usize, usize),
}

/// Below this `|u x v|^2 / (|u|^2 |v|^2)` (the squared sine of the angle) two edges count as
/// parallel and their distance is taken at an endpoint (where it is attained for exactly
/// parallel edges, and within `1e-5` of an edge's length of it below the threshold). Edges
/// parallel up to rounding (two face diagonals of a grid whose cells are `1.0 / 10` by
/// `0.3 / 3`) have a squared sine near `1e-16`: above a smaller threshold their lines'
/// closest points came from a singular system, and coplanar ones got distance 0. Edge pairs
/// this close to parallel carry a mollifier of about `1e-7` on their barrier, so the switch
/// to an endpoint moves no force that matters.
const PARALLEL: f64 = 1e-10;

/// The distance from `p` to the triangle `abc` (closed), and its form on `[p, a, b, c]`.
pub(crate) fn point_triangle(
    p: &Vector3<f64>,
    a: &Vector3<f64>,
    b: &Vector3<f64>,
    c: &Vector3<f64>,
) -> (f64, Form) {
    let form = point_triangle_form(p, a, b, c);
    let points = [*p, *a, *b, *c];
    (squared(form, &points).max(0.0).sqrt(), form)
}

/// The Voronoi region of the triangle that `p` projects into (Ericson, Real-Time Collision
/// Detection, 5.1.5).
fn point_triangle_form(
    p: &Vector3<f64>,
    a: &Vector3<f64>,
    b: &Vector3<f64>,
    c: &Vector3<f64>,
) -> Form {
    if a == b || b == c || c == a {
        // Coinciding corners: the triangle is a segment or a point, and the regions below
        // would pick a line through two equal points (a NaN distance). The nearest of its
        // edges, a zero-length one being a point.
        let points = [*p, *a, *b, *c];
        return [(1, 2), (2, 3), (3, 1)]
            .into_iter()
            .map(|(j, k)| point_segment_form(&points, 0, j, k))
            .min_by(|f, g| squared(*f, &points).total_cmp(&squared(*g, &points)))
            .expect("three edges");
    }
    let (ab, ac, ap) = (b - a, c - a, p - a);
    let (d1, d2) = (ab.dot(&ap), ac.dot(&ap));
    if d1 <= 0.0 && d2 <= 0.0 {
        return Form::PointPoint(0, 1);
    }
    let bp = p - b;
    let (d3, d4) = (ab.dot(&bp), ac.dot(&bp));
    if d3 >= 0.0 && d4 <= d3 {
        return Form::PointPoint(0, 2);
    }
    if d1 * d4 - d3 * d2 <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return Form::PointLine(0, 1, 2);
    }
    let cp = p - c;
    let (d5, d6) = (ab.dot(&cp), ac.dot(&cp));
    if d6 >= 0.0 && d5 <= d6 {
        return Form::PointPoint(0, 3);
    }
    if d5 * d2 - d1 * d6 <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return Form::PointLine(0, 3, 1);
    }
    if d3 * d6 - d5 * d4 <= 0.0 && d4 - d3 >= 0.0 && d5 - d6 >= 0.0 {
        return Form::PointLine(0, 2, 3);
    }
    Form::PointPlane(0, 1, 2, 3)
}

/// The distance between the segments `a0 a1` and `b0 b1` (closed), and its form on
/// `[a0, a1, b0, b1]`.
pub(crate) fn edge_edge(
    a0: &Vector3<f64>,
    a1: &Vector3<f64>,
    b0: &Vector3<f64>,
    b1: &Vector3<f64>,
) -> (f64, Form) {
    let points = [*a0, *a1, *b0, *b1];
    let (u, v, w) = (a1 - a0, b1 - b0, a0 - b0);
    let (uu, uv, vv, uw, vw) = (u.dot(&u), u.dot(&v), v.dot(&v), u.dot(&w), v.dot(&w));
    let den = uu * vv - uv * uv;
    if den > PARALLEL * uu * vv {
        // The lines' closest points, if both lie inside the segments.
        let s = (uv * vw - vv * uw) / den;
        let t = (uu * vw - uv * uw) / den;
        if s > 0.0 && s < 1.0 && t > 0.0 && t < 1.0 {
            let form = Form::LineLine(0, 1, 2, 3);
            return (squared(form, &points).max(0.0).sqrt(), form);
        }
    }
    // Otherwise an endpoint of one segment is closest to the other segment.
    [(0, 2, 3), (1, 2, 3), (2, 0, 1), (3, 0, 1)]
        .into_iter()
        .map(|(i, j, k)| {
            let form = point_segment_form(&points, i, j, k);
            (squared(form, &points).max(0.0).sqrt(), form)
        })
        .fold((f64::INFINITY, Form::PointPoint(0, 2)), |best, next| {
            if next.0 < best.0 { next } else { best }
        })
}

/// The form of the distance from point `i` to the segment `j k`.
fn point_segment_form(points: &[Vector3<f64>; 4], i: usize, j: usize, k: usize) -> Form {
    let e = points[k] - points[j];
    if e == Vector3::zeros() {
        // A segment of zero length is a point (t would be 0 / 0).
        return Form::PointPoint(i, j);
    }
    let t = (points[i] - points[j]).dot(&e) / e.norm_squared();
    if t <= 0.0 {
        Form::PointPoint(i, j)
    } else if t >= 1.0 {
        Form::PointPoint(i, k)
    } else {
        Form::PointLine(i, j, k)
    }
}

/// The closest points of `form` on `x` as weights of the four points: `sum w_k x_k` is the
/// vector from the closest point of the second primitive to that of the first (its norm is
/// the distance); weights of points the form does not use are 0.
pub(crate) fn closest_weights(form: Form, x: &[Vector3<f64>; 4]) -> [f64; 4] {
    let mut w = [0.0; 4];
    // `t` along `a -> b` of the point nearest `p` (clamped to the segment).
    let along = |p: &Vector3<f64>, a: &Vector3<f64>, b: &Vector3<f64>| {
        let e = b - a;
        ((p - a).dot(&e) / e.norm_squared().max(f64::MIN_POSITIVE)).clamp(0.0, 1.0)
    };
    match form {
        Form::PointPoint(i, j) => {
            w[i] = 1.0;
            w[j] = -1.0;
        }
        Form::PointLine(i, j, k) => {
            let t = along(&x[i], &x[j], &x[k]);
            w[i] = 1.0;
            w[j] = -(1.0 - t);
            w[k] = -t;
        }
        Form::PointPlane(i, j, k, l) => {
            // Barycentric coordinates of the projection (the form is chosen only when it
            // falls inside the triangle).
            let (e1, e2, q) = (x[k] - x[j], x[l] - x[j], x[i] - x[j]);
            let (a, b, c) = (e1.dot(&e1), e1.dot(&e2), e2.dot(&e2));
            let (d, e) = (e1.dot(&q), e2.dot(&q));
            let det = (a * c - b * b).max(f64::MIN_POSITIVE);
            let (u, v) = ((c * d - b * e) / det, (a * e - b * d) / det);
            w[i] = 1.0;
            w[j] = -(1.0 - u - v);
            w[k] = -u;
            w[l] = -v;
        }
        Form::LineLine(i, j, k, l) => {
            // The interior closest points of two non-parallel lines.
            let (d1, d2, r) = (x[j] - x[i], x[l] - x[k], x[i] - x[k]);
            let (a, b, c) = (d1.dot(&d1), d1.dot(&d2), d2.dot(&d2));
            let (d, e) = (d1.dot(&r), d2.dot(&r));
            let det = (a * c - b * b).max(f64::MIN_POSITIVE);
            let s = ((b * e - c * d) / det).clamp(0.0, 1.0);
            let t = ((a * e - b * d) / det).clamp(0.0, 1.0);
            w[i] = 1.0 - s;
            w[j] = s;
            w[k] = -(1.0 - t);
            w[l] = -t;
        }
    }
    w
}

/// The squared distance of `form` on `points`.
pub(crate) fn squared(form: Form, x: &[Vector3<f64>; 4]) -> f64 {
    match form {
        Form::PointPoint(i, j) => (x[i] - x[j]).norm_squared(),
        Form::PointLine(i, j, k) => {
            let e = x[k] - x[j];
            (x[i] - x[j]).cross(&e).norm_squared() / e.norm_squared()
        }
        Form::PointPlane(i, j, k, l) => {
            let n = (x[k] - x[j]).cross(&(x[l] - x[j]));
            let h = (x[i] - x[j]).dot(&n);
            h * h / n.norm_squared()
        }
        Form::LineLine(i, j, k, l) => {
            let n = (x[j] - x[i]).cross(&(x[l] - x[k]));
            let h = (x[k] - x[i]).dot(&n);
            h * h / n.norm_squared()
        }
    }
}

/// The squared distance of `form` on `points`, with its derivatives.
pub(crate) fn squared_jet(form: Form, x: &[JetPoint; 4]) -> Jet {
    match form {
        Form::PointPoint(i, j) => {
            let d = sub(&x[i], &x[j]);
            dot(&d, &d)
        }
        Form::PointLine(i, j, k) => {
            let e = sub(&x[k], &x[j]);
            let c = cross(&sub(&x[i], &x[j]), &e);
            dot(&c, &c) * dot(&e, &e).recip()
        }
        Form::PointPlane(i, j, k, l) => {
            let n = cross(&sub(&x[k], &x[j]), &sub(&x[l], &x[j]));
            let h = dot(&sub(&x[i], &x[j]), &n);
            h * h * dot(&n, &n).recip()
        }
        Form::LineLine(i, j, k, l) => {
            let n = cross(&sub(&x[j], &x[i]), &sub(&x[l], &x[k]));
            let h = dot(&sub(&x[k], &x[i]), &n);
            h * h * dot(&n, &n).recip()
        }
    }
}

/// IPC's mollifier of two edges' energy, `m(c) = (2 - c / eps) c / eps` below `eps` and 1
/// above, of `c = |(a1 - a0) x (b1 - b0)|^2`: it takes an edge pair's barrier smoothly to
/// zero as the edges become parallel, where their distance's form jumps.
pub(crate) fn mollifier(x: &[JetPoint; 4], eps: f64) -> Jet {
    let n = cross(&sub(&x[1], &x[0]), &sub(&x[3], &x[2]));
    let c = dot(&n, &n);
    if c.value >= eps {
        return Jet::constant(1.0);
    }
    let r = c.value / eps;
    c.map((2.0 - r) * r, (2.0 - 2.0 * r) / eps, -2.0 / (eps * eps))
}

#[cfg(test)]
mod closest_tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        /// The weighted sum of the closest points has the pair's distance as its norm, and
        /// the weights on each primitive are a convex combination.
        #[test]
        fn closest_weights_give_the_distance(c in prop::array::uniform12(-1.0f64..1.0), edges in any::<bool>()) {
            let x: [Vector3<f64>; 4] = std::array::from_fn(|k| Vector3::new(c[3 * k], c[3 * k + 1], c[3 * k + 2]));
            let (d, form) = if edges {
                edge_edge(&x[0], &x[1], &x[2], &x[3])
            } else {
                point_triangle(&x[0], &x[1], &x[2], &x[3])
            };
            // Non-degenerate primitives apart (random points can make a sliver triangle or
            // two almost parallel edges, which contact never measures without its mollifier).
            let area = (x[2] - x[1]).cross(&(x[3] - x[1])).norm();
            let turn = (x[1] - x[0]).cross(&(x[3] - x[2])).norm();
            prop_assume!(d > 1e-3 && if edges { turn > 1e-2 } else { area > 1e-2 });
            let w = closest_weights(form, &x);
            let v: Vector3<f64> = (0..4).map(|k| x[k] * w[k]).sum();
            prop_assert!((v.norm() - d).abs() <= 1e-9 * (1.0 + d), "{} {d} {form:?}", v.norm());
            let first = if edges { w[0] + w[1] } else { w[0] };
            // (Which primitive is "first" depends on the form: the sign may flip.)
            prop_assert!((first.abs() - 1.0).abs() < 1e-12 && (w.iter().sum::<f64>()).abs() < 1e-12);
            prop_assert!(w.iter().all(|w| (-1.0 - 1e-12..=1.0 + 1e-12).contains(w)));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::jet::variables;
    use proptest::prelude::*;

    /// A triangle with two or three coinciding corners is a segment or a point: finite
    /// distances, the segment's or the point's (issue 58: NaN froze a body above such a
    /// triangle). An edge of zero length is a point too.
    #[test]
    fn coinciding_corners_give_the_segment_or_point_distance() {
        let p = Vector3::new(0.3, 0.4, 1.0);
        let (a, c) = (Vector3::new(0.0, 0.0, 0.0), Vector3::new(1.0, 0.0, 0.0));
        // Two equal corners: the segment a c, nearest at (0.3, 0, 0).
        for (x, y, z) in [(a, a, c), (a, c, c), (c, a, a), (a, c, a)] {
            let (d, _) = point_triangle(&p, &x, &y, &z);
            assert!((d - (0.4f64.powi(2) + 1.0).sqrt()).abs() < 1e-15, "{d}");
        }
        // Three: the point.
        let (d, form) = point_triangle(&p, &a, &a, &a);
        assert_eq!(d, p.norm());
        assert!(matches!(form, Form::PointPoint(0, _)));
        // An edge of zero length against a segment: the point's distance to it.
        let (d, _) = edge_edge(&p, &p, &a, &c);
        assert!((d - (0.4f64.powi(2) + 1.0).sqrt()).abs() < 1e-15, "{d}");
    }

    fn point() -> impl Strategy<Value = Vector3<f64>> {
        prop::array::uniform3(-1.0f64..1.0).prop_map(Vector3::from)
    }

    /// The least distance over samples of the closed primitives: an upper bound of the
    /// distance that a fine sampling approaches.
    fn sampled(f: impl Fn(f64, f64) -> f64) -> f64 {
        let n = 60;
        let mut best = f64::INFINITY;
        for i in 0..=n {
            for j in 0..=n {
                best = best.min(f(i as f64 / n as f64, j as f64 / n as f64));
            }
        }
        best
    }

    /// Two face diagonals of a grid, parallel up to rounding and coplanar, are their true
    /// distance apart (they were 0 apart when rounding passed for an angle).
    #[test]
    fn edges_parallel_up_to_rounding_are_their_true_distance_apart() {
        let (hx, hy) = (1.0 / 10.0, 0.3 / 3.0);
        let at = |i: f64, j: f64| Vector3::new(-0.1 + i * hx, -0.1 + j * hy, -0.05);
        let (a0, a1, b0, b1) = (at(2.0, 2.0), at(3.0, 3.0), at(3.0, 1.0), at(4.0, 2.0));
        let (u, v) = (a1 - a0, b1 - b0);
        // Parallel, but not to the old test's rounding (its squared sine, 1e-16).
        let sine2 = 1.0 - u.dot(&v).powi(2) / (u.norm_squared() * v.norm_squared());
        assert!(sine2 > 1e-20, "{sine2}");
        let (d, _) = edge_edge(&a0, &a1, &b0, &b1);
        assert!((d - 0.1 * 2f64.sqrt()).abs() < 1e-12, "{d}");
    }

    proptest! {
        /// The point-triangle distance is at most, and close to, the least sampled distance.
        #[test]
        fn point_triangle_matches_sampling(p in point(), a in point(), b in point(), c in point()) {
            prop_assume!((b - a).cross(&(c - a)).norm() > 0.05);
            let (d, _) = point_triangle(&p, &a, &b, &c);
            let s = sampled(|u, v| {
                let (u, v) = if u + v > 1.0 { (1.0 - u, 1.0 - v) } else { (u, v) };
                (p - (a + (b - a) * u + (c - a) * v)).norm()
            });
            prop_assert!(d <= s + 1e-12 && s - d < 0.05, "{d} {s}");
        }

        /// The edge-edge distance is at most, and close to, the least sampled distance.
        #[test]
        fn edge_edge_matches_sampling(a0 in point(), a1 in point(), b0 in point(), b1 in point()) {
            prop_assume!((a1 - a0).norm() > 0.05 && (b1 - b0).norm() > 0.05);
            let (d, _) = edge_edge(&a0, &a1, &b0, &b1);
            let s = sampled(|u, v| ((a0 + (a1 - a0) * u) - (b0 + (b1 - b0) * v)).norm());
            prop_assert!(d <= s + 1e-12 && s - d < 0.05, "{d} {s}");
        }

        /// Every form's gradient and Hessian match central differences.
        #[test]
        fn forms_differentiate_exactly(
            x in prop::array::uniform4(point()),
            which in 0usize..4,
        ) {
            let form = [
                Form::PointPoint(0, 2),
                Form::PointLine(1, 2, 3),
                Form::PointPlane(0, 1, 2, 3),
                Form::LineLine(0, 1, 2, 3),
            ][which];
            prop_assume!((x[3] - x[2]).cross(&(x[1] - x[0])).norm() > 0.1);
            prop_assume!((x[2] - x[1]).cross(&(x[3] - x[1])).norm() > 0.1);
            let jet = squared_jet(form, &variables(&x));
            prop_assert!((jet.value - squared(form, &x)).abs() < 1e-12);
            check_derivatives(&jet, |y| squared_jet(form, &variables(y)), &x)?;
        }

        /// The mollifier's derivatives, below its threshold.
        #[test]
        fn mollifier_differentiates_exactly(x in prop::array::uniform4(point())) {
            let n = (x[1] - x[0]).cross(&(x[3] - x[2])).norm_squared();
            prop_assume!(n > 1e-3);
            let eps = 2.0 * n;
            let jet = mollifier(&variables(&x), eps);
            prop_assert!(jet.value > 0.0 && jet.value < 1.0);
            check_derivatives(&jet, |y| mollifier(&variables(y), eps), &x)?;
        }
    }

    fn check_derivatives(
        jet: &Jet,
        f: impl Fn(&[Vector3<f64>; 4]) -> Jet,
        x: &[Vector3<f64>; 4],
    ) -> Result<(), TestCaseError> {
        let h = 1e-6;
        for i in 0..12 {
            let (mut xp, mut xm) = (*x, *x);
            xp[i / 3][i % 3] += h;
            xm[i / 3][i % 3] -= h;
            let (fp, fm) = (f(&xp), f(&xm));
            let fd = (fp.value - fm.value) / (2.0 * h);
            let scale = 1.0 + jet.gradient.amax();
            prop_assert!(
                (fd - jet.gradient[i]).abs() < 1e-6 * scale,
                "{i}: {fd} {}",
                jet.gradient[i]
            );
            let col = (fp.gradient - fm.gradient) / (2.0 * h);
            let hscale = 1.0 + jet.hessian.amax();
            for j in 0..12 {
                prop_assert!((col[j] - jet.hessian[(i, j)]).abs() < 1e-5 * hscale);
            }
        }
        Ok(())
    }
}

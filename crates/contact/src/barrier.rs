//! IPC's log barrier on a distance (Li et al. 2020, Eq. 6).

/// `b(d) = -kappa (d - dhat)^2 ln(d / dhat)` for `0 < d < dhat`, zero beyond `dhat`: a
/// potential that is `C^2` at `dhat`, grows without bound as `d -> 0`, and is convex on
/// `(0, dhat)`. `kappa` (N/m) sets its stiffness, `dhat` (m) the distance where it starts.
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
pub struct Barrier {
    /// Activation distance (m).
    pub dhat: f64,
    /// Stiffness (N/m: the barrier is an energy per squared length times a log).
    pub kappa: f64,
}

impl Barrier {
    /// The barrier of activation distance `dhat` (m) and stiffness `kappa` (N/m).
    pub fn new(dhat: f64, kappa: f64) -> Self {
        Self { dhat, kappa }
    }

    /// `b(d)`; infinite at and below 0.
    pub fn value(&self, d: f64) -> f64 {
        if d <= 0.0 {
            return f64::INFINITY;
        }
        if d >= self.dhat {
            return 0.0;
        }
        let e = d - self.dhat;
        -self.kappa * e * e * (d / self.dhat).ln()
    }

    /// `b'(d)`, negative on `(0, dhat)`: the barrier pushes apart.
    pub fn first(&self, d: f64) -> f64 {
        if d >= self.dhat || d <= 0.0 {
            return 0.0;
        }
        let e = d - self.dhat;
        -self.kappa * (2.0 * e * (d / self.dhat).ln() + e * e / d)
    }

    /// `b''(d)`, positive on `(0, dhat)`.
    pub fn second(&self, d: f64) -> f64 {
        if d >= self.dhat || d <= 0.0 {
            return 0.0;
        }
        let e = d - self.dhat;
        -self.kappa * (2.0 * (d / self.dhat).ln() + 4.0 * e / d - e * e / (d * d))
    }

    /// The secant slope of `b'` from `d` to `to`: the curvature that makes Newton's linear
    /// model of the barrier force exact at `to`, where a step is predicted to carry the
    /// distance (`b''(d)` when `to` is not positive, where `b'` does not exist, or within
    /// rounding of `d`). Non-negative, as `b'` does not decrease.
    pub fn secant(&self, d: f64, to: f64) -> f64 {
        if to <= 0.0 || (to - d).abs() <= 1e-12 * self.dhat {
            return self.second(d);
        }
        ((self.first(to) - self.first(d)) / (to - d)).max(0.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    const B: Barrier = Barrier {
        dhat: 1e-3,
        kappa: 2.5e4,
    };

    proptest! {
        /// Central differences of `b` and `b'` match `b'` and `b''`.
        #[test]
        fn derivatives_match_differences(t in 0.02f64..0.98) {
            let d = t * B.dhat;
            let h = 1e-6 * B.dhat;
            let fd1 = (B.value(d + h) - B.value(d - h)) / (2.0 * h);
            let fd2 = (B.first(d + h) - B.first(d - h)) / (2.0 * h);
            prop_assert!((fd1 - B.first(d)).abs() <= 1e-6 * B.first(d).abs().max(1e-3), "{fd1} {}", B.first(d));
            prop_assert!((fd2 - B.second(d)).abs() <= 1e-6 * B.second(d).abs().max(1.0), "{fd2} {}", B.second(d));
            prop_assert!(B.value(d) > 0.0 && B.first(d) < 0.0 && B.second(d) > 0.0);
        }
    }

    proptest! {
        /// The secant makes the linear model exact at its end, tends to `b''` as the ends
        /// meet, and is never negative (the barrier is convex and flat beyond `dhat`).
        #[test]
        fn the_secant_is_exact_at_its_end(s in 0.02f64..1.5, t in 0.02f64..1.5) {
            let (d, to) = (s * B.dhat, t * B.dhat);
            let slope = B.secant(d, to);
            prop_assert!(slope >= 0.0);
            if (to - d).abs() > 1e-6 * B.dhat {
                let model = B.first(d) + slope * (to - d);
                prop_assert!((model - B.first(to)).abs() <= 1e-9 * B.first(d).abs().max(B.first(to).abs()).max(1e-6));
            }
            // (Near `dhat` both `b'` and `b''` vanish and the difference is rounding.)
            if s < 0.95 {
                let near = B.secant(d, d * (1.0 + 1e-7));
                prop_assert!((near - B.second(d)).abs() <= 1e-5 * B.second(d));
            }
        }
    }

    #[test]
    fn is_c2_at_dhat_and_infinite_at_contact() {
        let below = B.dhat * (1.0 - 1e-9);
        assert!(B.value(below) < 1e-20);
        assert!(B.first(below).abs() < 1e-10);
        assert!(B.second(below).abs() < 1e-3);
        assert_eq!(B.value(B.dhat), 0.0);
        assert_eq!(B.value(0.0), f64::INFINITY);
        // Unbounded, if slowly: `kappa dhat^2 ln(dhat / d)`.
        assert!(B.value(1e-300) > B.value(1e-100) && B.value(1e-100) > 2.0 * B.value(1e-12));
    }
}

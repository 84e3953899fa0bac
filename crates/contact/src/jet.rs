//! Second-order forward differentiation over the 12 coordinates of a contact pair (a point
//! and a triangle, or two edges): each quantity carries its value, gradient and Hessian, so
//! that the distances, the mollifier and the barrier compose with exact derivatives.

use std::ops::{Add, Mul, Neg, Sub};

use nalgebra::{SMatrix, SVector, Vector3};

/// The coordinates of a pair: four points of three coordinates.
pub(crate) const N: usize = 12;

/// A value with its gradient and Hessian in the pair's 12 coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Jet {
    pub(crate) value: f64,
    pub(crate) gradient: SVector<f64, N>,
    pub(crate) hessian: SMatrix<f64, N, N>,
}

impl Jet {
    /// A constant.
    pub(crate) fn constant(value: f64) -> Self {
        Self {
            value,
            gradient: SVector::zeros(),
            hessian: SMatrix::zeros(),
        }
    }

    /// Coordinate `i` itself.
    fn variable(value: f64, i: usize) -> Self {
        let mut jet = Self::constant(value);
        jet.gradient[i] = 1.0;
        jet
    }

    /// `g(self)` from `g`, `g'` and `g''` at the value (the chain rule).
    pub(crate) fn map(self, g: f64, g1: f64, g2: f64) -> Self {
        Self {
            value: g,
            gradient: self.gradient * g1,
            hessian: self.hessian * g1 + self.gradient * self.gradient.transpose() * g2,
        }
    }

    /// `1 / self`.
    pub(crate) fn recip(self) -> Self {
        let v = self.value;
        self.map(1.0 / v, -1.0 / (v * v), 2.0 / (v * v * v))
    }

    /// `sqrt(self)` (the value must be positive).
    pub(crate) fn sqrt(self) -> Self {
        let s = self.value.sqrt();
        self.map(s, 0.5 / s, -0.25 / (s * s * s))
    }
}

impl Add for Jet {
    type Output = Jet;
    fn add(self, o: Jet) -> Jet {
        Jet {
            value: self.value + o.value,
            gradient: self.gradient + o.gradient,
            hessian: self.hessian + o.hessian,
        }
    }
}

impl Sub for Jet {
    type Output = Jet;
    fn sub(self, o: Jet) -> Jet {
        Jet {
            value: self.value - o.value,
            gradient: self.gradient - o.gradient,
            hessian: self.hessian - o.hessian,
        }
    }
}

impl Neg for Jet {
    type Output = Jet;
    fn neg(self) -> Jet {
        Jet {
            value: -self.value,
            gradient: -self.gradient,
            hessian: -self.hessian,
        }
    }
}

impl Mul for Jet {
    type Output = Jet;
    fn mul(self, o: Jet) -> Jet {
        let cross = self.gradient * o.gradient.transpose();
        Jet {
            value: self.value * o.value,
            gradient: self.gradient * o.value + o.gradient * self.value,
            hessian: self.hessian * o.value + o.hessian * self.value + cross + cross.transpose(),
        }
    }
}

impl Mul<f64> for Jet {
    type Output = Jet;
    fn mul(self, s: f64) -> Jet {
        Jet {
            value: self.value * s,
            gradient: self.gradient * s,
            hessian: self.hessian * s,
        }
    }
}

/// A point of jets.
pub(crate) type JetPoint = [Jet; 3];

/// The four points of a pair as variables: point `k` is coordinates `3k..3k + 3`.
pub(crate) fn variables(points: &[Vector3<f64>; 4]) -> [JetPoint; 4] {
    std::array::from_fn(|k| std::array::from_fn(|c| Jet::variable(points[k][c], 3 * k + c)))
}

pub(crate) fn sub(a: &JetPoint, b: &JetPoint) -> JetPoint {
    std::array::from_fn(|c| a[c] - b[c])
}

pub(crate) fn dot(a: &JetPoint, b: &JetPoint) -> Jet {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

pub(crate) fn cross(a: &JetPoint, b: &JetPoint) -> JetPoint {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `f(x) = x0 x1 / (1 + x2^2)^(1/2)`: gradient and Hessian against central differences.
    #[test]
    fn products_quotients_and_roots_differentiate_exactly() {
        let f = |x: &[f64; 3]| -> Jet {
            let p = [
                Vector3::new(x[0], x[1], x[2]),
                Vector3::zeros(),
                Vector3::zeros(),
                Vector3::zeros(),
            ];
            let v = variables(&p);
            let (a, b, c) = (v[0][0], v[0][1], v[0][2]);
            a * b * (Jet::constant(1.0) + c * c).sqrt().recip()
        };
        let x = [0.7, -1.3, 0.4];
        let jet = f(&x);
        let h = 1e-6;
        for i in 0..3 {
            let (mut xp, mut xm) = (x, x);
            xp[i] += h;
            xm[i] -= h;
            let (fp, fm) = (f(&xp), f(&xm));
            let fd = (fp.value - fm.value) / (2.0 * h);
            assert!(
                (fd - jet.gradient[i]).abs() < 1e-8,
                "{fd} {}",
                jet.gradient[i]
            );
            for j in 0..3 {
                let fd2 = (fp.gradient[j] - fm.gradient[j]) / (2.0 * h);
                assert!((fd2 - jet.hessian[(i, j)]).abs() < 1e-7);
            }
        }
        assert_eq!(jet.hessian, jet.hessian.transpose());
    }
}

//! The energy models. Formulas, derivations and parameter mappings are in `docs/theory.md`.

use std::ops::AddAssign;

use nalgebra::{Matrix3, Vector3};

use crate::isotropic::{self, Isotropic, SignedSvd, cofactor, guard};
use crate::lame::Lame;
use crate::material::{Material, Matrix9, project_psd, vec9};

/// The unit Lame pair of split term `k`: `(1, 0)` for the `mu` term, `(0, 1)` for `lambda`.
fn unit_lame(k: usize) -> Lame {
    match k {
        0 => Lame {
            mu: 1.0,
            lambda: 0.0,
        },
        1 => Lame {
            mu: 0.0,
            lambda: 1.0,
        },
        _ => panic!("a Lame model has 2 split terms, asked for term {k}"),
    }
}

/// The Lame split: each model is linear in `(mu, lambda)`, so term `k` is the model
/// evaluated at the unit pair of [`unit_lame`].
macro_rules! lame_split {
    () => {
        fn num_terms(&self) -> usize {
            2
        }

        fn coefficients(&self, out: &mut [f64]) {
            out[0] = self.lame.mu;
            out[1] = self.lame.lambda;
        }

        #[track_caller]
        #[allow(clippy::needless_update)]
        fn term_psi(&self, k: usize, f: &Matrix3<f64>) -> f64 {
            Self {
                lame: unit_lame(k),
                ..*self
            }
            .psi(f)
        }

        #[track_caller]
        #[allow(clippy::needless_update)]
        fn term_first_piola(&self, k: usize, f: &Matrix3<f64>) -> Matrix3<f64> {
            Self {
                lame: unit_lame(k),
                ..*self
            }
            .first_piola(f)
        }

        #[track_caller]
        #[allow(clippy::needless_update)]
        fn term_dp_df(&self, k: usize, f: &Matrix3<f64>) -> Matrix9 {
            Self {
                lame: unit_lame(k),
                ..*self
            }
            .dp_df(f)
        }
    };
}

/// `9x9` identity-like term `sum_ij e_ij (x) e_ij` plus scaled helpers.
fn identity9(scale: f64) -> Matrix9 {
    Matrix9::identity() * scale
}

// ---------------------------------------------------------------------------------------

/// Linear isotropic elasticity (small strain): `Psi = mu eps:eps + lambda/2 tr(eps)^2`,
/// `eps = (F + F^T)/2 - I`. Not rotation invariant: large rotations produce spurious stress.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LinearElastic {
    /// Lame pair.
    pub lame: Lame,
}

impl Material for LinearElastic {
    fn name(&self) -> &'static str {
        "linear elastic"
    }

    fn psi(&self, f: &Matrix3<f64>) -> f64 {
        let eps = (f + f.transpose()) * 0.5 - Matrix3::identity();
        self.lame.mu * eps.norm_squared() + 0.5 * self.lame.lambda * eps.trace().powi(2)
    }

    fn first_piola(&self, f: &Matrix3<f64>) -> Matrix3<f64> {
        let eps = (f + f.transpose()) * 0.5 - Matrix3::identity();
        eps * (2.0 * self.lame.mu) + Matrix3::identity() * (self.lame.lambda * eps.trace())
    }

    fn dp(&self, _f: &Matrix3<f64>, df: &Matrix3<f64>) -> Matrix3<f64> {
        (df + df.transpose()) * self.lame.mu + Matrix3::identity() * (self.lame.lambda * df.trace())
    }

    fn dp_df(&self, _f: &Matrix3<f64>) -> Matrix9 {
        let Lame { mu, lambda } = self.lame;
        let mut out = identity9(mu);
        let id = vec9(&Matrix3::identity());
        out.ger(lambda, &id, &id, 1.0);
        // mu dF^T: entry (ij, ji) gains mu.
        for i in 0..3 {
            for j in 0..3 {
                out[(3 * j + i, 3 * i + j)] += mu;
            }
        }
        out
    }

    /// The tangent's eigenvalues are `2 mu` (deviatoric), `0` (rotations) and
    /// `2 mu + 3 lambda` (volumetric): PSD for every valid Lame pair.
    fn dp_df_projected(&self, f: &Matrix3<f64>) -> Matrix9 {
        let t = self.dp_df(f);
        if self.lame.mu >= 0.0 && 2.0 * self.lame.mu + 3.0 * self.lame.lambda >= 0.0 {
            t
        } else {
            project_psd(&t)
        }
    }

    lame_split!();
}

// ---------------------------------------------------------------------------------------

/// Corotated linear elasticity: `Psi = mu ||F - R||^2 + lambda/2 tr(R^T F - I)^2` with the
/// polar decomposition `F = R S` (from the rotation-fixed SVD, robust to inversion).
///
/// By default the tangent is exact, including the rotation's variation. With
/// `lagged_rotation` (the "warped stiffness" of Mueller et al.), `R` is held fixed in the
/// tangent: `dP = R [mu (R^T dF + dF^T R) + lambda tr(R^T dF) I]`, which is PSD and cheaper
/// but not the Hessian of `Psi`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CorotatedLinear {
    /// Lame pair.
    pub lame: Lame,
    /// Hold the rotation fixed in the tangent.
    pub lagged_rotation: bool,
}

impl Isotropic for CorotatedLinear {
    fn psi_s(&self, s: &Vector3<f64>) -> f64 {
        let d = s - Vector3::repeat(1.0);
        self.lame.mu * d.norm_squared() + 0.5 * self.lame.lambda * (s.sum() - 3.0).powi(2)
    }
    fn grad_s(&self, s: &Vector3<f64>) -> Vector3<f64> {
        (s - Vector3::repeat(1.0)) * (2.0 * self.lame.mu)
            + Vector3::repeat(self.lame.lambda * (s.sum() - 3.0))
    }
    fn hess_s(&self, _s: &Vector3<f64>) -> Matrix3<f64> {
        Matrix3::identity() * (2.0 * self.lame.mu) + Matrix3::repeat(self.lame.lambda)
    }
    fn pair(&self, s: &Vector3<f64>, i: usize, j: usize, _k: usize) -> (f64, f64) {
        let Lame { mu, lambda } = self.lame;
        let b = 2.0 * mu + (2.0 * lambda * (s.sum() - 3.0) - 4.0 * mu) / guard(s[i] + s[j]);
        (2.0 * mu, b)
    }
}

impl CorotatedLinear {
    fn lagged_tangent(&self, r: &Matrix3<f64>) -> Matrix9 {
        let Lame { mu, lambda } = self.lame;
        let mut out = identity9(mu);
        let rv = vec9(r);
        out.ger(lambda, &rv, &rv, 1.0);
        // mu R dF^T R: entry (ij, kl) gains mu R_il R_kj.
        for j in 0..3 {
            for i in 0..3 {
                for l in 0..3 {
                    for k in 0..3 {
                        out[(3 * j + i, 3 * l + k)] += mu * r[(i, l)] * r[(k, j)];
                    }
                }
            }
        }
        out
    }
}

impl Material for CorotatedLinear {
    fn name(&self) -> &'static str {
        "corotated linear"
    }

    fn psi(&self, f: &Matrix3<f64>) -> f64 {
        self.psi_s(&SignedSvd::new(f).s)
    }

    fn first_piola(&self, f: &Matrix3<f64>) -> Matrix3<f64> {
        isotropic::first_piola(self, &SignedSvd::new(f))
    }

    fn dp(&self, f: &Matrix3<f64>, df: &Matrix3<f64>) -> Matrix3<f64> {
        let svd = SignedSvd::new(f);
        if self.lagged_rotation {
            let r = svd.rotation();
            let rdf = r.transpose() * df;
            r * ((rdf + rdf.transpose()) * self.lame.mu
                + Matrix3::identity() * (self.lame.lambda * rdf.trace()))
        } else {
            isotropic::dp(self, &svd, df)
        }
    }

    fn dp_df(&self, f: &Matrix3<f64>) -> Matrix9 {
        let svd = SignedSvd::new(f);
        if self.lagged_rotation {
            self.lagged_tangent(&svd.rotation())
        } else {
            isotropic::tangent(self, &svd, false)
        }
    }

    fn dp_df_projected(&self, f: &Matrix3<f64>) -> Matrix9 {
        if self.lagged_rotation {
            // Eigenvalues 2 mu, 0 and 2 mu + 3 lambda, as for linear elasticity.
            let t = self.dp_df(f);
            if 2.0 * self.lame.mu + 3.0 * self.lame.lambda >= 0.0 {
                t
            } else {
                project_psd(&t)
            }
        } else {
            isotropic::tangent(self, &SignedSvd::new(f), true)
        }
    }

    fn first_piola_and_tangent(&self, f: &Matrix3<f64>, project: bool) -> (Matrix3<f64>, Matrix9) {
        let svd = SignedSvd::new(f);
        let p = isotropic::first_piola(self, &svd);
        let t = if self.lagged_rotation {
            let t = self.lagged_tangent(&svd.rotation());
            if project && 2.0 * self.lame.mu + 3.0 * self.lame.lambda < 0.0 {
                project_psd(&t)
            } else {
                t
            }
        } else {
            isotropic::tangent(self, &svd, project)
        };
        (p, t)
    }

    lame_split!();
}

// ---------------------------------------------------------------------------------------

/// Fixed corotated (Stomakhin et al. 2012): `Psi = mu ||F - R||^2 + lambda/2 (J - 1)^2`,
/// defined and smooth through inversion.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FixedCorotated {
    /// Lame pair.
    pub lame: Lame,
}

impl Isotropic for FixedCorotated {
    fn psi_s(&self, s: &Vector3<f64>) -> f64 {
        let j = s.product();
        self.lame.mu * (s - Vector3::repeat(1.0)).norm_squared()
            + 0.5 * self.lame.lambda * (j - 1.0).powi(2)
    }
    fn grad_s(&self, s: &Vector3<f64>) -> Vector3<f64> {
        let j = s.product();
        (s - Vector3::repeat(1.0)) * (2.0 * self.lame.mu)
            + cofactor(s) * (self.lame.lambda * (j - 1.0))
    }
    fn hess_s(&self, s: &Vector3<f64>) -> Matrix3<f64> {
        let Lame { mu, lambda } = self.lame;
        let (j, c) = (s.product(), cofactor(s));
        let mut h = c * c.transpose() * lambda;
        for (i, jj, k) in isotropic::PAIRS {
            h[(i, jj)] += lambda * (j - 1.0) * s[k];
            h[(jj, i)] += lambda * (j - 1.0) * s[k];
        }
        h + Matrix3::identity() * (2.0 * mu)
    }
    fn pair(&self, s: &Vector3<f64>, i: usize, j: usize, k: usize) -> (f64, f64) {
        let Lame { mu, lambda } = self.lame;
        let t = lambda * (s.product() - 1.0) * s[k];
        (2.0 * mu - t, 2.0 * mu + t - 4.0 * mu / guard(s[i] + s[j]))
    }
}

impl Material for FixedCorotated {
    fn name(&self) -> &'static str {
        "fixed corotated"
    }
    fn psi(&self, f: &Matrix3<f64>) -> f64 {
        self.psi_s(&SignedSvd::new(f).s)
    }
    fn first_piola(&self, f: &Matrix3<f64>) -> Matrix3<f64> {
        isotropic::first_piola(self, &SignedSvd::new(f))
    }
    fn dp(&self, f: &Matrix3<f64>, df: &Matrix3<f64>) -> Matrix3<f64> {
        isotropic::dp(self, &SignedSvd::new(f), df)
    }
    fn dp_df(&self, f: &Matrix3<f64>) -> Matrix9 {
        isotropic::tangent(self, &SignedSvd::new(f), false)
    }
    fn dp_df_projected(&self, f: &Matrix3<f64>) -> Matrix9 {
        isotropic::tangent(self, &SignedSvd::new(f), true)
    }
    fn first_piola_and_tangent(&self, f: &Matrix3<f64>, project: bool) -> (Matrix3<f64>, Matrix9) {
        let svd = SignedSvd::new(f);
        (
            isotropic::first_piola(self, &svd),
            isotropic::tangent(self, &svd, project),
        )
    }
    lame_split!();
}

// ---------------------------------------------------------------------------------------

/// St. Venant-Kirchhoff: `Psi = mu E:E + lambda/2 tr(E)^2`, `E = (F^T F - I)/2`.
/// Defined everywhere, but it softens under compression and its energy does not resist
/// full inversion.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StVenantKirchhoff {
    /// Lame pair.
    pub lame: Lame,
}

impl StVenantKirchhoff {
    fn strain_stress(&self, f: &Matrix3<f64>) -> (Matrix3<f64>, Matrix3<f64>) {
        let e = (f.transpose() * f - Matrix3::identity()) * 0.5;
        let s = e * (2.0 * self.lame.mu) + Matrix3::identity() * (self.lame.lambda * e.trace());
        (e, s)
    }
}

impl Isotropic for StVenantKirchhoff {
    fn psi_s(&self, s: &Vector3<f64>) -> f64 {
        let e = (s.component_mul(s) - Vector3::repeat(1.0)) * 0.5;
        self.lame.mu * e.norm_squared() + 0.5 * self.lame.lambda * e.sum().powi(2)
    }
    fn grad_s(&self, s: &Vector3<f64>) -> Vector3<f64> {
        let Lame { mu, lambda } = self.lame;
        let ic = s.norm_squared();
        Vector3::from_fn(|i, _| mu * (s[i] * s[i] - 1.0) * s[i] + 0.5 * lambda * (ic - 3.0) * s[i])
    }
    fn hess_s(&self, s: &Vector3<f64>) -> Matrix3<f64> {
        let Lame { mu, lambda } = self.lame;
        let ic = s.norm_squared();
        let mut h = s * s.transpose() * lambda;
        for i in 0..3 {
            h[(i, i)] += mu * (3.0 * s[i] * s[i] - 1.0) + 0.5 * lambda * (ic - 3.0);
        }
        h
    }
    fn pair(&self, s: &Vector3<f64>, i: usize, j: usize, _k: usize) -> (f64, f64) {
        let Lame { mu, lambda } = self.lame;
        let vol = 0.5 * lambda * (s.norm_squared() - 3.0);
        let sq = s[i] * s[i] + s[j] * s[j] - 1.0;
        (mu * (sq + s[i] * s[j]) + vol, mu * (sq - s[i] * s[j]) + vol)
    }
}

impl Material for StVenantKirchhoff {
    fn name(&self) -> &'static str {
        "St. Venant-Kirchhoff"
    }
    fn psi(&self, f: &Matrix3<f64>) -> f64 {
        let (e, _) = self.strain_stress(f);
        self.lame.mu * e.norm_squared() + 0.5 * self.lame.lambda * e.trace().powi(2)
    }
    fn first_piola(&self, f: &Matrix3<f64>) -> Matrix3<f64> {
        f * self.strain_stress(f).1
    }
    fn dp(&self, f: &Matrix3<f64>, df: &Matrix3<f64>) -> Matrix3<f64> {
        let (_, s) = self.strain_stress(f);
        let ftdf = f.transpose() * df;
        let de = (ftdf + ftdf.transpose()) * 0.5;
        let ds = de * (2.0 * self.lame.mu) + Matrix3::identity() * (self.lame.lambda * de.trace());
        df * s + f * ds
    }
    fn dp_df(&self, f: &Matrix3<f64>) -> Matrix9 {
        let Lame { mu, lambda } = self.lame;
        let (_, s) = self.strain_stress(f);
        let fft = f * f.transpose();
        let fv = vec9(f);
        let mut out = Matrix9::zeros();
        out.ger(lambda, &fv, &fv, 0.0);
        // dP_ij/dF_kl = delta_ik S_lj + mu F_il F_kj + mu delta_jl (F F^T)_ik + lambda F_ij F_kl
        for j in 0..3 {
            for i in 0..3 {
                for l in 0..3 {
                    for k in 0..3 {
                        let mut v = mu * f[(i, l)] * f[(k, j)];
                        if i == k {
                            v += s[(l, j)];
                        }
                        if j == l {
                            v += mu * fft[(i, k)];
                        }
                        out[(3 * j + i, 3 * l + k)] += v;
                    }
                }
            }
        }
        out
    }
    fn dp_df_projected(&self, f: &Matrix3<f64>) -> Matrix9 {
        isotropic::tangent(self, &SignedSvd::new(f), true)
    }
    lame_split!();
}

// ---------------------------------------------------------------------------------------

/// Compressible Neo-Hookean: `Psi = mu/2 (I1 - 3) - mu log J + lambda/2 (log J)^2`,
/// `I1 = ||F||^2`, `J = det F`.
///
/// Defined for `J > 0` only: at `J <= 0` [`Material::admissible`] is false and `psi` is
/// `+inf`, so a line search rejects such a state and assembly reports the element.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NeoHookean {
    /// Lame pair.
    pub lame: Lame,
}

impl Isotropic for NeoHookean {
    fn psi_s(&self, s: &Vector3<f64>) -> f64 {
        let lj = s.product().ln();
        let Lame { mu, lambda } = self.lame;
        0.5 * mu * (s.norm_squared() - 3.0) - mu * lj + 0.5 * lambda * lj * lj
    }
    fn grad_s(&self, s: &Vector3<f64>) -> Vector3<f64> {
        let Lame { mu, lambda } = self.lame;
        let c = lambda * s.product().ln() - mu;
        Vector3::from_fn(|i, _| mu * s[i] + c / s[i])
    }
    fn hess_s(&self, s: &Vector3<f64>) -> Matrix3<f64> {
        let Lame { mu, lambda } = self.lame;
        let c = mu - lambda * s.product().ln();
        let inv = s.map(|x| 1.0 / x);
        let mut h = inv * inv.transpose() * lambda;
        for i in 0..3 {
            h[(i, i)] += mu + c * inv[i] * inv[i];
        }
        h
    }
    fn pair(&self, s: &Vector3<f64>, i: usize, j: usize, _k: usize) -> (f64, f64) {
        let Lame { mu, lambda } = self.lame;
        let t = (mu - lambda * s.product().ln()) / (s[i] * s[j]);
        (mu + t, mu - t)
    }
}

impl NeoHookean {
    fn inv_t(f: &Matrix3<f64>) -> Matrix3<f64> {
        f.try_inverse().unwrap_or_else(Matrix3::zeros).transpose()
    }

    /// `mu Id + lambda vec(F^-T) vec(F^-T)^T + (mu - lambda log J) T`, with
    /// `T[(ij), (kl)] = (F^-T)_il (F^-T)_kj`, written in one pass.
    #[inline]
    fn tangent_with(&self, fit: &Matrix3<f64>, log_j: f64) -> Matrix9 {
        let Lame { mu, lambda } = self.lame;
        let c = mu - lambda * log_j;
        let mut out = Matrix9::zeros();
        for l in 0..3 {
            for k in 0..3 {
                let col = 3 * l + k;
                let lv = lambda * fit[(k, l)];
                for j in 0..3 {
                    let cj = c * fit[(k, j)];
                    for i in 0..3 {
                        out[(3 * j + i, col)] = lv * fit[(i, j)] + cj * fit[(i, l)];
                    }
                }
                out[(col, col)] += mu;
            }
        }
        out
    }
}

impl Material for NeoHookean {
    fn name(&self) -> &'static str {
        "Neo-Hookean"
    }
    fn admissible(&self, f: &Matrix3<f64>) -> bool {
        f.determinant() > 0.0
    }
    fn psi(&self, f: &Matrix3<f64>) -> f64 {
        let j = f.determinant();
        if !(j > 0.0) {
            return f64::INFINITY;
        }
        let Lame { mu, lambda } = self.lame;
        let lj = j.ln();
        0.5 * mu * (f.norm_squared() - 3.0) - mu * lj + 0.5 * lambda * lj * lj
    }
    fn first_piola(&self, f: &Matrix3<f64>) -> Matrix3<f64> {
        let Lame { mu, lambda } = self.lame;
        let fit = Self::inv_t(f);
        (f - fit) * mu + fit * (lambda * f.determinant().ln())
    }
    fn dp(&self, f: &Matrix3<f64>, df: &Matrix3<f64>) -> Matrix3<f64> {
        let Lame { mu, lambda } = self.lame;
        let fit = Self::inv_t(f);
        let c = mu - lambda * f.determinant().ln();
        df * mu + fit * df.transpose() * fit * c + fit * (lambda * fit.dot(df))
    }
    fn dp_df(&self, f: &Matrix3<f64>) -> Matrix9 {
        self.tangent_with(&Self::inv_t(f), f.determinant().ln())
    }
    fn first_piola_and_tangent(&self, f: &Matrix3<f64>, project: bool) -> (Matrix3<f64>, Matrix9) {
        if project {
            let svd = SignedSvd::new(f);
            return (
                isotropic::first_piola(self, &svd),
                isotropic::tangent(self, &svd, true),
            );
        }
        let Lame { mu, lambda } = self.lame;
        let (fit, lj) = (Self::inv_t(f), f.determinant().ln());
        (
            (f - fit) * mu + fit * (lambda * lj),
            self.tangent_with(&fit, lj),
        )
    }
    fn dp_df_projected(&self, f: &Matrix3<f64>) -> Matrix9 {
        isotropic::tangent(self, &SignedSvd::new(f), true)
    }
    lame_split!();
}

// ---------------------------------------------------------------------------------------

/// Stable Neo-Hookean (Smith, de Goes, Kim 2018), inversion-safe and rest-stable.
///
/// In its own parameters `(mu_s, lambda_s)`:
/// `Psi = mu_s [(I1 - 3)/2 - 3/4 (J - 1) - (log(I1 + 1) - log 4)/2] + lambda_s/2 (J - 1)^2`,
/// which is the paper's `mu_s/2 (I1 - 3) + lambda_s/2 (J - alpha)^2 - mu_s/2 log(I1 + 1)`
/// with `alpha = 1 + 3 mu_s / (4 lambda_s)`, expanded and shifted by a constant so that
/// `Psi(I) = 0`. Its small-strain limit equals linear elasticity with the Lame pair
/// `(mu, lambda)` when `mu_s = 4/3 mu` and `lambda_s = lambda + 5/6 mu`; the model takes the
/// Lame pair and applies that mapping, so all models share one small-strain limit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StableNeoHookean {
    /// Lame pair (of the small-strain limit).
    pub lame: Lame,
}

impl StableNeoHookean {
    /// The model from the paper's own parameters `(mu_s, lambda_s)` (Smith et al. 2018,
    /// their Eq. 14 with `alpha = 1 + 3 mu_s / (4 lambda_s)`): the Lame pair of its
    /// small-strain limit is `mu = 3/4 mu_s`, `lambda = lambda_s - 5/6 mu`.
    ///
    /// # Errors
    /// [`crate::MaterialError`] when that pair is not a valid material.
    pub fn from_paper_parameters(mu_s: f64, lambda_s: f64) -> Result<Self, crate::MaterialError> {
        let mu = 0.75 * mu_s;
        Ok(Self {
            lame: Lame::try_new(mu, lambda_s - 5.0 / 6.0 * mu)?,
        })
    }

    /// `(mu_s, lambda_s)` of the paper from the Lame pair.
    pub fn paper_parameters(&self) -> (f64, f64) {
        let Lame { mu, lambda } = self.lame;
        (4.0 / 3.0 * mu, lambda + 5.0 / 6.0 * mu)
    }
}

/// Cofactor matrix `J F^-T`: columns `f1 x f2`, `f2 x f0`, `f0 x f1`.
fn cofactor_matrix(f: &Matrix3<f64>) -> Matrix3<f64> {
    let (f0, f1, f2) = (f.column(0), f.column(1), f.column(2));
    Matrix3::from_columns(&[f1.cross(&f2), f2.cross(&f0), f0.cross(&f1)])
}

impl Isotropic for StableNeoHookean {
    fn psi_s(&self, s: &Vector3<f64>) -> f64 {
        let (ms, ls) = self.paper_parameters();
        let (ic, j) = (s.norm_squared(), s.product());
        ms * (0.5 * (ic - 3.0) - 0.75 * (j - 1.0) - 0.5 * ((ic + 1.0).ln() - 4f64.ln()))
            + 0.5 * ls * (j - 1.0).powi(2)
    }
    fn grad_s(&self, s: &Vector3<f64>) -> Vector3<f64> {
        let (ms, ls) = self.paper_parameters();
        let (ic, j, c) = (s.norm_squared(), s.product(), cofactor(s));
        s * (ms * (1.0 - 1.0 / (ic + 1.0))) + c * (ls * (j - 1.0) - 0.75 * ms)
    }
    fn hess_s(&self, s: &Vector3<f64>) -> Matrix3<f64> {
        let (ms, ls) = self.paper_parameters();
        let (ic, j, c) = (s.norm_squared(), s.product(), cofactor(s));
        let q = 1.0 / (ic + 1.0);
        let mut h = s * s.transpose() * (2.0 * ms * q * q) + c * c.transpose() * ls;
        for (i, jj, k) in isotropic::PAIRS {
            let v = (ls * (j - 1.0) - 0.75 * ms) * s[k];
            h[(i, jj)] += v;
            h[(jj, i)] += v;
        }
        h + Matrix3::identity() * (ms * (1.0 - q))
    }
    fn pair(&self, s: &Vector3<f64>, _i: usize, _j: usize, k: usize) -> (f64, f64) {
        let (ms, ls) = self.paper_parameters();
        let (ic, j) = (s.norm_squared(), s.product());
        let base = ms * (1.0 - 1.0 / (ic + 1.0));
        let t = (0.75 * ms - ls * (j - 1.0)) * s[k];
        (base + t, base - t)
    }
}

impl Material for StableNeoHookean {
    fn name(&self) -> &'static str {
        "stable Neo-Hookean"
    }
    fn psi(&self, f: &Matrix3<f64>) -> f64 {
        let (ms, ls) = self.paper_parameters();
        let (ic, j) = (f.norm_squared(), f.determinant());
        ms * (0.5 * (ic - 3.0) - 0.75 * (j - 1.0) - 0.5 * ((ic + 1.0).ln() - 4f64.ln()))
            + 0.5 * ls * (j - 1.0).powi(2)
    }
    fn first_piola(&self, f: &Matrix3<f64>) -> Matrix3<f64> {
        let (ms, ls) = self.paper_parameters();
        let (ic, j) = (f.norm_squared(), f.determinant());
        f * (ms * (1.0 - 1.0 / (ic + 1.0))) + cofactor_matrix(f) * (ls * (j - 1.0) - 0.75 * ms)
    }
    fn dp(&self, f: &Matrix3<f64>, df: &Matrix3<f64>) -> Matrix3<f64> {
        let (ms, ls) = self.paper_parameters();
        let (ic, j) = (f.norm_squared(), f.determinant());
        let q = 1.0 / (ic + 1.0);
        let g = cofactor_matrix(f);
        let (f0, f1, f2) = (f.column(0), f.column(1), f.column(2));
        let (d0, d1, d2) = (df.column(0), df.column(1), df.column(2));
        let dg = Matrix3::from_columns(&[
            d1.cross(&f2) + f1.cross(&d2),
            d2.cross(&f0) + f2.cross(&d0),
            d0.cross(&f1) + f0.cross(&d1),
        ]);
        df * (ms * (1.0 - q))
            + f * (2.0 * ms * q * q * f.dot(df))
            + g * (ls * g.dot(df))
            + dg * (ls * (j - 1.0) - 0.75 * ms)
    }
    fn dp_df(&self, f: &Matrix3<f64>) -> Matrix9 {
        let (ms, ls) = self.paper_parameters();
        let (ic, j) = (f.norm_squared(), f.determinant());
        let q = 1.0 / (ic + 1.0);
        let (fv, gv) = (vec9(f), vec9(&cofactor_matrix(f)));
        let mut out = identity9(ms * (1.0 - q));
        out.ger(2.0 * ms * q * q, &fv, &fv, 1.0);
        out.ger(ls, &gv, &gv, 1.0);
        // Hessian of J: block (i, j) = d g_i / d f_j, skew matrices of the columns of F.
        let c = ls * (j - 1.0) - 0.75 * ms;
        let skew = |k: usize| f.column(k).into_owned().cross_matrix() * c;
        let blocks = [
            (0, 1, 2, -1.0),
            (0, 2, 1, 1.0),
            (1, 0, 2, 1.0),
            (1, 2, 0, -1.0),
            (2, 0, 1, -1.0),
            (2, 1, 0, 1.0),
        ];
        for (bi, bj, col, sign) in blocks {
            let m = skew(col) * sign;
            out.fixed_view_mut::<3, 3>(3 * bi, 3 * bj).add_assign(&m);
        }
        out
    }
    fn dp_df_projected(&self, f: &Matrix3<f64>) -> Matrix9 {
        isotropic::tangent(self, &SignedSvd::new(f), true)
    }
    lame_split!();
}

#[cfg(test)]
mod tests {
    use super::*;

    const LAME: Lame = Lame {
        mu: 1.3,
        lambda: 4.1,
    };

    /// `R diag(s) Q` with two fixed, generic rotations.
    fn rotated(s: &Vector3<f64>) -> Matrix3<f64> {
        let r = nalgebra::Rotation3::from_euler_angles(0.3, -1.1, 0.7).into_inner();
        let q = nalgebra::Rotation3::from_euler_angles(-0.4, 0.2, 2.0).into_inner();
        r * Matrix3::from_diagonal(s) * q
    }

    /// The analytic projection (clamped eigensystem) is the nearest PSD tangent: equal to
    /// the numerical projection of the exact tangent, at states where the tangent is
    /// indefinite, including states whose scaling Hessian is itself indefinite (the branch
    /// that decomposes it) and an inverted one.
    #[test]
    fn analytic_projection_equals_the_numerical_one() {
        let l = LAME;
        let stretches = [
            Vector3::new(0.5, 0.6, 0.7),
            Vector3::new(3.0, 2.0, 2.0),
            Vector3::new(1.4, 0.9, 0.8),
            Vector3::new(1.1, 0.9, -0.5),
        ];
        let (mut indefinite_h, mut compared) = (0, 0);
        let mut check = |name: &str,
                         m: &dyn Material,
                         iso: &dyn Fn(&Vector3<f64>) -> Matrix3<f64>,
                         s: Vector3<f64>| {
            let f = rotated(&s);
            if !m.admissible(&f) {
                return;
            }
            let exact = m.dp_df(&f);
            let numerical = project_psd(&exact);
            let analytic = m.dp_df_projected(&f);
            assert!(
                (analytic - numerical).norm() < 1e-9 * exact.norm(),
                "{name} at {s}: {}",
                (analytic - numerical).norm()
            );
            compared += 1;
            if nalgebra::SymmetricEigen::new(iso(&s)).eigenvalues.min() < 0.0 {
                indefinite_h += 1;
            }
        };
        let nh = NeoHookean { lame: l };
        let st = StVenantKirchhoff { lame: l };
        let sn = StableNeoHookean { lame: l };
        let fc = FixedCorotated { lame: l };
        for s in stretches {
            check("nh", &nh, &|s| nh.hess_s(s), s);
            check("stvk", &st, &|s| st.hess_s(s), s);
            check("snh", &sn, &|s| sn.hess_s(s), s);
            check("fixed corotated", &fc, &|s| fc.hess_s(s), s);
        }
        assert!(
            compared >= 14 && indefinite_h >= 3,
            "{compared} {indefinite_h}"
        );
    }

    /// The singular-value eigensystem reproduces each closed-form tangent, including at
    /// repeated singular values, where `a` and `b` rely on their closed forms.
    #[test]
    fn eigensystem_matches_closed_form_tangents() {
        let l = LAME;
        let cases = [
            Vector3::new(1.3, 0.8, 0.6),
            Vector3::new(1.0, 1.0, 1.0),
            Vector3::new(1.2, 1.2, 0.7),
        ];
        for s in cases {
            let f = rotated(&s);
            let svd = SignedSvd::new(&f);
            let check = |name: &str,
                         closed: Matrix9,
                         engine: Matrix9,
                         dp_closed: Matrix3<f64>,
                         dp_engine: Matrix3<f64>| {
                assert!(
                    (closed - engine).norm() < 1e-9 * closed.norm(),
                    "{name} at {s}: {}",
                    (closed - engine).norm()
                );
                assert!(
                    (dp_closed - dp_engine).norm() < 1e-9 * (1.0 + dp_closed.norm()),
                    "{name} dp at {s}"
                );
            };
            let df = Matrix3::new(0.1, -0.3, 0.2, 0.5, 0.1, -0.2, 0.3, 0.0, -0.4);
            let nh = NeoHookean { lame: l };
            check(
                "nh",
                nh.dp_df(&f),
                isotropic::tangent(&nh, &svd, false),
                nh.dp(&f, &df),
                isotropic::dp(&nh, &svd, &df),
            );
            let st = StVenantKirchhoff { lame: l };
            check(
                "stvk",
                st.dp_df(&f),
                isotropic::tangent(&st, &svd, false),
                st.dp(&f, &df),
                isotropic::dp(&st, &svd, &df),
            );
            let sn = StableNeoHookean { lame: l };
            check(
                "snh",
                sn.dp_df(&f),
                isotropic::tangent(&sn, &svd, false),
                sn.dp(&f, &df),
                isotropic::dp(&sn, &svd, &df),
            );
            assert!((nh.psi(&f) - nh.psi_s(&svd.s)).abs() < 1e-12 * (1.0 + nh.psi(&f).abs()));
            assert!(
                (st.first_piola(&f) - isotropic::first_piola(&st, &svd)).norm()
                    < 1e-12 * (1.0 + st.first_piola(&f).norm())
            );
            assert!(
                (sn.first_piola(&f) - isotropic::first_piola(&sn, &svd)).norm()
                    < 1e-12 * (1.0 + sn.first_piola(&f).norm())
            );
        }
    }
}

//! Stage 1 of force-model optimisation: the equation error.
//!
//! Plugging a data pair into the Backward-Euler residual (seed Eq. 8, docs/theory.md),
//! `M (v^n+1 - v^n) - dt M g = dt (f_e(x^n+1) - alpha M v^n+1 - gamma K(x^n+1) v^n+1)` on the
//! free DOFs. The materials' parameter split makes `f_e = J_f c` linear in the coefficients
//! `c` (for a single model, the Lame pair), and `gamma K v = J_k (gamma c)` linear in
//! `d = gamma c`. So `c`, `d` and `alpha` solve one linear least-squares problem over all
//! pairs: no simulation. Columns are scaled to unit norm before solving; optionally the
//! solution is kept non-negative (Lawson-Hanson active set on the normal equations).

use deform_assembly::Grouping;
use deform_integrator::Integrator;
use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

use crate::basis::Basis;
use crate::dataset::Trajectory;
pub use crate::error::FitError;

/// Every state of trajectory `index` holds `n` values; else which does not and what it has.
fn check_state_sizes(t: &Trajectory, index: usize, n: usize) -> Result<(), FitError> {
    let frames = t.x.iter().map(|f| ("position", f));
    let frames = frames.chain(t.v.iter().map(|f| ("velocity", f)));
    let Some((k, (what, f))) = (frames.enumerate()).find(|(_, (_, f))| f.len() != n) else {
        return Ok(());
    };
    let state = if what == "position" { k } else { k - t.x.len() };
    Err(FitError::Data {
        index,
        reason: format!(
            "{what} state {state} has {} values, expected {n} (3 per vertex of the scene's {} vertices)",
            f.len(),
            n / 3
        ),
    })
}

/// Options of the equation-error fit (`EquationErrorOptions::default().damping(true)`;
/// setters keep working when a field is added).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
#[non_exhaustive]
pub struct EquationErrorOptions {
    /// Also fit Rayleigh `alpha` and `gamma` (otherwise the integrator's values are used).
    pub damping: bool,
    /// Separate coefficients per mesh region.
    pub by_region: bool,
    /// Keep every coefficient non-negative.
    pub nonnegative: bool,
    /// Also fit each obstacle's coefficient of friction (a scene with contact; otherwise
    /// the scene's own coefficients are known forces, as the barrier's always are).
    pub friction: bool,
}

deform_setters::setters!(EquationErrorOptions {
    damping: bool,
    by_region: bool,
    nonnegative: bool,
    friction: bool,
});

impl Default for EquationErrorOptions {
    fn default() -> Self {
        Self {
            damping: false,
            by_region: false,
            nonnegative: true,
            friction: false,
        }
    }
}

/// The fitted coefficients and how well they explain the data.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[non_exhaustive]
pub struct EquationErrorFit {
    /// Coefficients, `groups x terms`, group-major (for one model per group: `[mu, lambda]`).
    pub coefficients: Vec<f64>,
    /// Terms per group.
    pub terms: usize,
    /// Region tags of the groups (one `0` group when not by region).
    pub groups: Vec<u32>,
    /// Rayleigh `alpha` (fitted, or the integrator's).
    pub alpha: f64,
    /// Rayleigh `gamma` (fitted, or the integrator's).
    pub gamma: f64,
    /// `||A p - b|| / ||b||` at the solution.
    pub relative_residual: f64,
    /// Equations used (free DOFs x pairs).
    pub equations: usize,
    /// The barrier's stiffness (N/m), fitted in a scene with contact whose data touch.
    #[serde(default)]
    pub kappa: Option<f64>,
    /// Each obstacle's coefficient of friction, when fitted (else empty).
    #[serde(default)]
    pub friction: Vec<f64>,
}

/// Why a stage-1 estimate cannot be used as a model (and so cannot start stage 2).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Unusable {
    /// A group's Lame pair is no material: the non-negative least squares put a coefficient
    /// on its bound (typically `mu = 0` when noise in the positions swamps the accelerations).
    InvalidPair {
        /// The group (its index in `groups`).
        group: usize,
        /// Its `(mu, lambda)`.
        pair: (f64, f64),
    },
    /// The fit explains (almost) nothing of the data: relative residual at least 0.99.
    NoFit {
        /// The relative residual.
        relative_residual: f64,
    },
    /// Not run: a training trajectory observes only markers, and the equation error needs
    /// whole states.
    MarkersOnly {
        /// The trajectory (its index among the training ones).
        trajectory: usize,
    },
}

impl std::fmt::Display for Unusable {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Unusable::InvalidPair { group, pair } => write!(
                f,
                "group {group}: (mu, lambda) = {pair:?} is no material (the data do not determine it; noisy positions?)"
            ),
            Unusable::NoFit { relative_residual } => write!(
                f,
                "relative residual {relative_residual:.3}: the equation error explains nothing of the data"
            ),
            Unusable::MarkersOnly { trajectory } => write!(
                f,
                "not run: training trajectory {trajectory} observes only markers, and the equation error needs whole states"
            ),
        }
    }
}

impl EquationErrorFit {
    /// Why the estimate cannot be used as a model, or `None` when it can. An ensemble's
    /// members may be zero (a member the data do not support); a single model's pair must
    /// be a material.
    pub fn unusable(&self) -> Option<Unusable> {
        if !(self.relative_residual < 0.99) {
            return Some(Unusable::NoFit {
                relative_residual: self.relative_residual,
            });
        }
        if self.terms != 2 {
            return None;
        }
        self.coefficients
            .chunks(2)
            .enumerate()
            .find(|(_, c)| deform_materials::Lame::try_new(c[0], c[1]).is_err())
            .map(|(group, c)| Unusable::InvalidPair {
                group,
                pair: (c[0], c[1]),
            })
    }
}

/// Fits the coefficients of the integrator's material (its term split) and optionally the
/// Rayleigh parameters to the pairs of `trajectories`, by equation error.
///
/// # Errors
/// [`FitError`].
pub fn fit_equation_error(
    sim: &Integrator,
    trajectories: &[&Trajectory],
    options: EquationErrorOptions,
) -> Result<EquationErrorFit, FitError> {
    let asm = sim.assembly();
    let grouping = if options.by_region {
        Grouping::by_region(asm)
    } else {
        Grouping::global(asm)
    };
    equation_error(sim, trajectories, &grouping, None, options)
}

/// How a coefficient field is laid out over the elements.
#[derive(Debug, Clone, PartialEq)]
pub enum FieldLayout {
    /// One set of term coefficients per distinct label (one label per element: the element
    /// index for a per-element field, a region, a cluster), by increasing label.
    Labels(Vec<u32>),
    /// Weights of smooth basis functions.
    Smooth(Basis),
}

/// Stage 1 of a coefficient field ([`fit_equation_error`] with `layout` instead of
/// `options.by_region`): the equation error is linear in a per-element field too, so one
/// least-squares solve gives every element's coefficients. Each column of the system
/// touches one element's vertices: the normal equations are accumulated row by row over
/// the non-zeros; the (non-negative) solve is dense in the number of coefficients (fine for
/// coarse meshes of some hundreds of elements). `groups` of the result are the labels, or
/// the basis functions' indices.
///
/// # Errors
/// [`FitError`], and [`FitError::Invalid`] for labels or a basis of another mesh.
pub fn fit_equation_error_field(
    sim: &Integrator,
    trajectories: &[&Trajectory],
    layout: &FieldLayout,
    options: EquationErrorOptions,
) -> Result<EquationErrorFit, FitError> {
    let asm = sim.assembly();
    let invalid = |e: String| FitError::Invalid(format!("field layout: {e}"));
    match layout {
        FieldLayout::Labels(labels) => {
            let grouping =
                Grouping::from_labels(asm, labels).map_err(|e| invalid(e.to_string()))?;
            equation_error(sim, trajectories, &grouping, None, options)
        }
        FieldLayout::Smooth(basis) => {
            if basis.num_elements() != asm.num_elements() {
                let n = (basis.num_elements(), asm.num_elements());
                return Err(invalid(format!(
                    "a basis over {} elements, {} in the mesh",
                    n.0, n.1
                )));
            }
            let grouping = Grouping::per_element(asm);
            equation_error(sim, trajectories, &grouping, Some(basis), options)
        }
    }
}

/// The equation-error fit of coefficients per group of `grouping`, or per function of
/// `basis` (with the per-element grouping).
fn equation_error(
    sim: &Integrator,
    trajectories: &[&Trajectory],
    grouping: &Grouping,
    basis: Option<&Basis>,
    options: EquationErrorOptions,
) -> Result<EquationErrorFit, FitError> {
    let asm = sim.assembly();
    let dt = sim.options().dt;
    let terms = asm.materials().max_terms();
    let sets = basis.map_or(grouping.num_groups(), Basis::num_functions);
    let nc = terms * sets;
    let contact = ContactForces::new(sim, options.friction)?;
    // Coefficients, then damping's, then contact's (`kappa`, `mu kappa` per obstacle).
    let first_mu = if options.damping { 2 * nc + 1 } else { nc };
    let p = first_mu + contact.as_ref().map_or(0, ContactForces::unknowns);
    // The non-zeros of row `i` of a term Jacobian in the field's coefficients, as
    // `(offset + column, scale * value)`.
    let nonzeros = |jacobian: &[f64], i: usize, offset: usize, scale: f64| {
        let width = jacobian.len() / asm.num_dofs();
        let row = &jacobian[i * width..(i + 1) * width];
        let row = match basis {
            Some(b) => std::borrow::Cow::Owned(b.contract(row, terms)),
            None => std::borrow::Cow::Borrowed(row),
        };
        let nz = row.iter().enumerate().filter(|(_, v)| **v != 0.0);
        nz.map(|(j, v)| (offset + j, scale * v)).collect::<Vec<_>>()
    };
    let n = asm.num_dofs();
    let free = sim.dofs().free_dofs();
    let mass = sim.mass();
    let (alpha0, gamma0) = (sim.options().alpha, sim.options().gamma);
    let mut g = DMatrix::<f64>::zeros(p, p);
    let mut h = DVector::<f64>::zeros(p);
    let mut bb = 0.0;
    let mut equations = 0;
    for (ti, t) in trajectories.iter().enumerate() {
        if t.observed.is_some() {
            return Err(FitError::Data {
                index: ti,
                reason: "observes only some vertices: the equation error needs whole states (use the output error)".into(),
            });
        }
        check_state_sizes(t, ti, n)?;
        let mut external = external_at(sim, t, ti, t.start_time + dt)?;
        for step in 0..t.steps() {
            let (x0, x1, v0, v1) = (&t.x[step], &t.x[step + 1], &t.v[step], &t.v[step + 1]);
            let fail = |source| FitError::Assembly {
                trajectory: ti,
                step: step + 1,
                source,
            };
            let jf = asm.term_forces(x1, grouping).map_err(fail)?;
            // Rows of A on the free DOFs, as (column, value) non-zeros, and b.
            let mut rows: Vec<Vec<(usize, f64)>> =
                free.iter().map(|&i| nonzeros(&jf.data, i, 0, dt)).collect();
            let mut b = vec![0.0; n];
            let dv: Vec<f64> = v1.iter().zip(v0).map(|(a, b)| a - b).collect();
            asm.mass_apply(mass, &dv, &mut b).map_err(fail)?;
            // Gravity is the same at every step; loads may stop.
            if step > 0 && sim.num_loads() > 0 {
                let time = t.start_time + (step + 1) as f64 * dt;
                external = external_at(sim, t, ti, time)?;
            }
            for (bi, gi) in b.iter_mut().zip(&external) {
                *bi -= dt * gi;
            }
            if let Some(c) = &contact {
                let t0 = t.start_time + step as f64 * dt;
                c.add((t0, x0), x1, dt, &mut rows, (free, first_mu))
                    .map_err(|reason| FitError::Data {
                        index: ti,
                        reason: format!("step {}: {reason}", step + 1),
                    })?;
            }
            let mut mv = vec![0.0; n];
            asm.mass_apply(mass, v1, &mut mv).map_err(fail)?;
            if options.damping {
                let jk = asm
                    .term_stiffness_products(x1, v1, grouping)
                    .map_err(fail)?;
                for (row, &i) in rows.iter_mut().zip(free) {
                    row.extend(nonzeros(&jk.data, i, nc, -dt));
                    row.push((2 * nc, -dt * mv[i]));
                }
            } else {
                known_damping(asm, (alpha0, gamma0), (x1, v1, &mv), dt, &mut b).map_err(fail)?;
            }
            // Accumulate the normal equations on the free DOFs, over each row's non-zeros.
            for (row, &i) in rows.iter().zip(free) {
                for &(a, va) in row {
                    h[a] += va * b[i];
                    for &(c, vc) in row {
                        g[(a, c)] += va * vc;
                    }
                }
            }
            bb += free.iter().map(|&i| b[i] * b[i]).sum::<f64>();
            equations += free.len();
        }
    }
    if equations == 0 {
        return Err(FitError::NoData);
    }
    // Contact that the data never touch leaves its columns empty: zero coefficients.
    for c in first_mu..p {
        if g[(c, c)] == 0.0 {
            g[(c, c)] = 1.0;
        }
    }
    let y = solve_normal_equations(&g, &h, options.nonnegative)?;
    let yv = DVector::from_column_slice(&y);
    let residual2 = (bb - 2.0 * h.dot(&yv) + yv.dot(&(&g * &yv))).max(0.0);
    let coefficients = y[..nc].to_vec();
    let (alpha, gamma) = if options.damping {
        let d = &y[nc..2 * nc];
        let cc: f64 = coefficients.iter().map(|c| c * c).sum();
        let dc: f64 = d.iter().zip(&coefficients).map(|(a, b)| a * b).sum();
        (y[2 * nc], if cc > 0.0 { dc / cc } else { 0.0 })
    } else {
        (alpha0, gamma0)
    };
    Ok(EquationErrorFit {
        coefficients,
        terms,
        groups: match basis {
            Some(b) => (0..b.num_functions() as u32).collect(),
            None => grouping.labels().to_vec(),
        },
        alpha,
        gamma,
        relative_residual: (residual2 / bb.max(f64::MIN_POSITIVE)).sqrt(),
        equations,
        kappa: contact.as_ref().map(|_| y[first_mu]).filter(|k| *k > 0.0),
        friction: match y.get(first_mu) {
            Some(&kappa) if kappa > 0.0 => y[first_mu + 1..].iter().map(|c| c / kappa).collect(),
            _ => Vec::new(),
        },
    })
}

/// The least-squares solution of the normal equations `g y = h`, its columns scaled to unit
/// norm first, non-negative when asked.
fn solve_normal_equations(
    g: &DMatrix<f64>,
    h: &DVector<f64>,
    nonnegative: bool,
) -> Result<Vec<f64>, FitError> {
    let p = h.len();
    // Unit column scaling.
    let scale: Vec<f64> = (0..p).map(|a| g[(a, a)].sqrt()).collect();
    if scale.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
        return Err(FitError::Singular);
    }
    let gs = DMatrix::from_fn(p, p, |a, c| g[(a, c)] / (scale[a] * scale[c]));
    let hs = DVector::from_fn(p, |a, _| h[a] / scale[a]);
    let ys = if nonnegative {
        nnls_normal(&gs, &hs).ok_or(FitError::Singular)?
    } else {
        solve_spd(&gs, &hs).ok_or(FitError::Singular)?
    };
    Ok((0..p).map(|a| ys[a] / scale[a]).collect())
}

/// Known Rayleigh damping `(alpha, gamma)` at `(x1, v1)` (with `mv = M v1`) moves to the
/// right-hand side `b`, with the model's own K.
fn known_damping(
    asm: &deform_assembly::Assembly,
    (alpha, gamma): (f64, f64),
    (x1, v1, mv): (&[f64], &[f64], &[f64]),
    dt: f64,
    b: &mut [f64],
) -> Result<(), deform_assembly::AssemblyError> {
    if gamma == 0.0 && alpha == 0.0 {
        return Ok(());
    }
    let mut kv = vec![0.0; b.len()];
    if gamma != 0.0 {
        asm.tangents(x1, deform_assembly::Tangent::Exact)?
            .apply(v1, &mut kv);
    }
    for i in 0..b.len() {
        b[i] += dt * (alpha * mv[i] + gamma * kv[i]);
    }
    Ok(())
}

/// The contact forces of a step in the equation error. They are linear in the barrier's
/// stiffness `kappa` (the barrier and friction's normal force scale with it), which is a
/// column: the scene's own `kappa` may be the default one, chosen from a material that is
/// being fitted. Friction's coefficients are known (the scene's) or fitted: then each
/// obstacle's friction at unit `mu` is a column too, of coefficient `mu kappa`.
struct ContactForces {
    /// The barrier at unit `kappa`, with the scene's friction unless it is fitted.
    barrier: deform_integrator::ContactModel,
    /// The same at unit `mu`, when friction is fitted.
    friction: Option<deform_integrator::ContactModel>,
}

impl ContactForces {
    fn new(sim: &Integrator, fit_friction: bool) -> Result<Option<Self>, FitError> {
        let Some(model) = sim.contact() else {
            return match fit_friction {
                true => Err(FitError::Invalid(
                    "friction: the scene has no contact to fit the friction of".into(),
                )),
                false => Ok(None),
            };
        };
        let invalid = |e: deform_integrator::ContactError| FitError::Invalid(e.to_string());
        // The scene's whole potential (obstacles, mesh obstacles, self-contact, friction) at
        // unit stiffness.
        let unit = model.clone().with_stiffness(1.0).map_err(invalid)?;
        let (barrier, friction) = match fit_friction {
            false => (unit, None),
            true => {
                let eps = model.friction().map_or(1e-3, |(_, eps)| eps);
                let spec = deform_integrator::FrictionSpec::new(vec![1.0]).velocity_threshold(eps);
                let frictionless = unit.without_friction();
                let friction = frictionless.clone().with_friction(&spec).map_err(invalid)?;
                (frictionless, Some(friction))
            }
        };
        Ok(Some(Self { barrier, friction }))
    }

    /// Its columns: `kappa`, then `mu kappa` per obstacle when friction is fitted.
    fn unknowns(&self) -> usize {
        1 + self.friction.as_ref().map_or(0, |f| f.frictional())
    }

    /// Appends the step's contact columns (from `first`) to the rows of the free DOFs: the
    /// barrier's (and known friction's) forces at `x1` at unit `kappa`, and each obstacle's
    /// friction at unit `mu` and `kappa`, lagged at `x0`.
    fn add(
        &self,
        (t0, x0): (f64, &[f64]),
        x1: &[f64],
        dt: f64,
        rows: &mut [Vec<(usize, f64)>],
        (free, first): (&[usize], usize),
    ) -> Result<(), String> {
        let placed = |m| placed_for_step(m, t0, t0 + dt);
        let barrier = placed(&self.barrier);
        let mut columns = vec![vec![0.0; x1.len()]];
        barrier
            .evaluate(x1, Some(&mut columns[0]), None)
            .map_err(|e| e.to_string())?;
        let lag = barrier.lag_friction(x0, dt);
        barrier.add_friction(&lag, x1, Some(&mut columns[0]), None);
        if let Some(friction) = self.friction.as_ref().map(placed) {
            let lag = friction.lag_friction(x0, dt);
            for o in 0..friction.frictional() {
                let part = deform_integrator::FrictionLag::default()
                    .pairs(
                        lag.pairs
                            .iter()
                            .filter(|p| p.obstacle == o)
                            .cloned()
                            .collect(),
                    )
                    .threshold(lag.threshold);
                let mut f = vec![0.0; x1.len()];
                friction.add_friction(&part, x1, Some(&mut f), None);
                columns.push(f);
            }
        }
        for (c, f) in columns.iter().enumerate() {
            for (row, &i) in rows.iter_mut().zip(free) {
                if f[i] != 0.0 {
                    row.push((first + c, dt * f[i]));
                }
            }
        }
        Ok(())
    }
}

/// `m` with its moving obstacles where the integrator had them for the step from `t0` to
/// `t1`: at its end, their friction lagged where they were at its start (`m` itself when
/// nothing moves).
pub(crate) fn placed_for_step(
    m: &deform_integrator::ContactModel,
    t0: f64,
    t1: f64,
) -> std::borrow::Cow<'_, deform_integrator::ContactModel> {
    if m.motions().is_empty() {
        return std::borrow::Cow::Borrowed(m);
    }
    let mut m = m.clone();
    m.set_step(t0, t1);
    std::borrow::Cow::Owned(m)
}

/// Solves the SPD system `G y = h` (Cholesky, or `None` if singular).
/// The external forces on trajectory `ti` at time `time`: its conditions' gravity and loads.
fn external_at(
    sim: &Integrator,
    t: &Trajectory,
    ti: usize,
    time: f64,
) -> Result<Vec<f64>, FitError> {
    sim.external_forces_under(&t.conditions, time)
        .map_err(|e| FitError::Data {
            index: ti,
            reason: e.to_string(),
        })
}

fn solve_spd(g: &DMatrix<f64>, h: &DVector<f64>) -> Option<DVector<f64>> {
    let chol = g.clone().cholesky()?;
    let y = chol.solve(h);
    y.iter().all(|v| v.is_finite()).then_some(y)
}

/// Lawson-Hanson non-negative least squares on the normal equations: minimises
/// `1/2 y^T G y - h^T y` subject to `y >= 0`.
fn nnls_normal(g: &DMatrix<f64>, h: &DVector<f64>) -> Option<DVector<f64>> {
    let p = h.len();
    let mut x = DVector::<f64>::zeros(p);
    let mut passive = vec![false; p];
    let tol = 1e-12 * h.amax().max(1e-300);
    for _outer in 0..3 * p + 10 {
        let w = h - g * &x;
        let candidate = (0..p)
            .filter(|&j| !passive[j] && w[j] > tol)
            .max_by(|&a, &b| w[a].total_cmp(&w[b]));
        let Some(j) = candidate else {
            return Some(x);
        };
        passive[j] = true;
        for _inner in 0..3 * p + 10 {
            let idx: Vec<usize> = (0..p).filter(|&k| passive[k]).collect();
            let gp = DMatrix::from_fn(idx.len(), idx.len(), |a, b| g[(idx[a], idx[b])]);
            let hp = DVector::from_fn(idx.len(), |a, _| h[idx[a]]);
            let zp = solve_spd(&gp, &hp)?;
            let mut z = DVector::<f64>::zeros(p);
            for (a, &k) in idx.iter().enumerate() {
                z[k] = zp[a];
            }
            if idx.iter().all(|&k| z[k] > 0.0) {
                x = z;
                break;
            }
            let step = idx
                .iter()
                .filter(|&&k| z[k] <= 0.0)
                .map(|&k| x[k] / (x[k] - z[k]))
                .fold(f64::INFINITY, f64::min);
            x += (z - &x) * step;
            for &k in &idx {
                if x[k] <= tol {
                    x[k] = 0.0;
                    passive[k] = false;
                }
            }
        }
    }
    Some(x)
}

/// The Lame pair and (E, nu) of a single-model fit of one group.
pub fn lame_of(fit: &EquationErrorFit, group: usize) -> Option<deform_materials::Lame> {
    if fit.terms != 2 {
        return None;
    }
    let c = &fit.coefficients[2 * group..2 * group + 2];
    deform_materials::Lame::try_new(c[0], c[1]).ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_estimate_that_is_no_material_or_explains_nothing_is_unusable() {
        let fit = |coefficients: Vec<f64>, terms, relative_residual| EquationErrorFit {
            groups: vec![0; coefficients.len() / terms],
            coefficients,
            terms,
            alpha: 0.0,
            gamma: 0.0,
            relative_residual,
            equations: 10,
            kappa: None,
            friction: Vec::new(),
        };
        assert_eq!(fit(vec![3e4, 5e4], 2, 0.1).unusable(), None);
        // The case: mu = lambda = 0 with residual 1.00 on noisy positions.
        assert_eq!(
            fit(vec![0.0, 0.0], 2, 1.0).unusable(),
            Some(Unusable::NoFit {
                relative_residual: 1.0
            })
        );
        assert_eq!(
            fit(vec![3e4, 5e4, 0.0, 5e4], 2, 0.3).unusable(),
            Some(Unusable::InvalidPair {
                group: 1,
                pair: (0.0, 5e4)
            })
        );
        assert!(fit(vec![1.0, 1.0], 2, f64::NAN).unusable().is_some());
        // An ensemble may leave members out.
        assert_eq!(fit(vec![3e4, 0.0, 0.0, 5e4], 4, 0.1).unusable(), None);
    }

    #[test]
    fn nnls_matches_a_brute_force_on_small_problems() {
        // G = A^T A for a fixed A; compare with enumerating all active sets.
        let a = DMatrix::from_row_slice(
            5,
            3,
            &[
                1.0, 2.0, 0.5, -1.0, 0.3, 2.0, 0.7, -0.2, 1.0, 0.0, 1.5, -1.0, 2.0, 0.1, 0.4,
            ],
        );
        for b in [
            DVector::from_column_slice(&[1.0, -2.0, 0.5, 3.0, -1.0]),
            DVector::from_column_slice(&[-1.0, -1.0, -1.0, -1.0, -1.0]),
            DVector::from_column_slice(&[0.3, 2.0, 1.0, 0.0, 1.0]),
        ] {
            let (g, h) = (a.transpose() * &a, a.transpose() * &b);
            let x = nnls_normal(&g, &h).unwrap();
            let cost = |y: &DVector<f64>| (&a * y - &b).norm_squared();
            let mut best = f64::INFINITY;
            for mask in 0..8u32 {
                let idx: Vec<usize> = (0..3).filter(|k| mask & (1 << k) != 0).collect();
                let mut y = DVector::zeros(3);
                if !idx.is_empty() {
                    let gp = DMatrix::from_fn(idx.len(), idx.len(), |i, j| g[(idx[i], idx[j])]);
                    let hp = DVector::from_fn(idx.len(), |i, _| h[idx[i]]);
                    let z = gp.cholesky().unwrap().solve(&hp);
                    if z.iter().any(|v| *v < 0.0) {
                        continue;
                    }
                    for (i, &k) in idx.iter().enumerate() {
                        y[k] = z[i];
                    }
                }
                best = best.min(cost(&y));
            }
            assert!(x.iter().all(|v| *v >= 0.0));
            assert!(
                (cost(&x) - best).abs() <= 1e-10 * best.max(1.0),
                "{} vs {best}",
                cost(&x)
            );
        }
    }
}

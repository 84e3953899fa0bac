//! What acts on the body from outside, per motion: per-vertex mass scales and the gravity
//! that follows them, the conditions of a motion (gravity, constraint motions, loads), and
//! the external forces they give at a time.

use super::*;

impl Integrator {
    /// Scales each vertex's lumped mass by `scale[v]` (finite, > 0; one per vertex), or
    /// restores the mesh's masses with `None`: a learned coarse model's mass distribution.
    /// Gravity forces follow the masses. The total mass is whatever the scales make it.
    ///
    /// # Errors
    /// [`IntegratorError::Invalid`] for a consistent mass matrix, a wrong length or a scale
    /// that is not finite and positive (naming the vertex).
    pub fn set_mass_scale(&mut self, scale: Option<&[f64]>) -> Result<(), IntegratorError> {
        let invalid = |reason: String| IntegratorError::Invalid {
            field: "mass_scale",
            reason,
        };
        let Mass::Lumped(current) = &self.mass else {
            return Err(invalid("needs the lumped mass".into()));
        };
        if let Some(scale) = scale {
            check_mass_scale(scale, current.len()).map_err(invalid)?;
        }
        let own = match self.mass_scale.take() {
            Some((_, own)) => own,
            None => current.clone(),
        };
        match scale {
            Some(scale) => {
                self.mass = Mass::Lumped(own.iter().zip(scale).map(|(m, s)| m * s).collect());
                self.mass_scale = Some((scale.to_vec(), own));
            }
            None => self.mass = Mass::Lumped(own),
        }
        self.update_gravity_forces()
    }

    /// The per-vertex mass scales set by [`Integrator::set_mass_scale`].
    pub fn mass_scale(&self) -> Option<&[f64]> {
        self.mass_scale.as_ref().map(|(s, _)| s.as_slice())
    }

    /// The mesh's own (unscaled) lumped vertex masses, or the row sums of the consistent
    /// mass.
    pub fn unscaled_vertex_masses(&self) -> Vec<f64> {
        match &self.mass_scale {
            Some((_, own)) => own.clone(),
            None => self.asm.vertex_masses(&self.mass),
        }
    }

    /// `M g` for the current mass and active gravity.
    pub(super) fn update_gravity_forces(&mut self) -> Result<(), IntegratorError> {
        self.gravity_forces = gravity_forces(&self.asm, &self.mass, self.gravity())?;
        Ok(())
    }

    /// The active gravity: the conditions', else the options' (the model's own).
    pub fn gravity(&self) -> [f64; 3] {
        self.conditions.gravity.unwrap_or(self.options.gravity)
    }

    /// The overrides of the model's gravity, constraint motions and loads in force.
    pub fn conditions(&self) -> &Conditions {
        &self.conditions
    }

    /// Steps from now on under `conditions` (the model's own where they say `None`;
    /// `Conditions::default()` restores the model's own): one model, motions made under
    /// different forcing.
    ///
    /// # Errors
    /// [`IntegratorError::Invalid`] naming the field when a value is not finite or there is
    /// not one motion per constraint or one force per load.
    pub fn set_conditions(&mut self, conditions: &Conditions) -> Result<(), IntegratorError> {
        self.check(conditions)?;
        let gravity_changed = conditions.gravity != self.conditions.gravity;
        self.conditions = conditions.clone();
        if gravity_changed {
            self.update_gravity_forces()?;
        }
        Ok(())
    }

    /// Refuses conditions that do not fit this model (see [`Conditions::validate`]).
    pub(super) fn check(&self, conditions: &Conditions) -> Result<(), IntegratorError> {
        conditions
            .validate(self.constraints.len(), self.loads.len())
            .map_err(|(field, reason)| IntegratorError::Invalid {
                field: "conditions",
                reason: format!("{field}: {reason}"),
            })
    }

    /// The motion of constraint `i` under the conditions in force.
    pub(super) fn motion(&self, i: usize) -> &Motion {
        match &self.conditions.motions {
            Some(m) => &m[i],
            None => &self.constraints[i].motion,
        }
    }

    /// Number of external loads.
    pub fn num_loads(&self) -> usize {
        self.loads.len()
    }

    /// The external forces at time `t`: gravity's `M g` and the loads acting at `t`.
    pub fn external_forces(&self, t: f64) -> Vec<f64> {
        let mut f = self.gravity_forces.clone();
        self.add_loads(&self.conditions, t, 1e-9 * self.options.dt, &mut f);
        f
    }

    /// [`Integrator::external_forces`] under other conditions than those in force (e.g. a
    /// trajectory's, for a fit that reads forces off data without stepping).
    ///
    /// # Errors
    /// As [`Integrator::set_conditions`].
    pub fn external_forces_under(
        &self,
        conditions: &Conditions,
        t: f64,
    ) -> Result<Vec<f64>, IntegratorError> {
        self.check(conditions)?;
        let g = conditions.gravity.unwrap_or(self.options.gravity);
        let mut f = if g == self.gravity() {
            self.gravity_forces.clone()
        } else {
            gravity_forces(&self.asm, &self.mass, g)?
        };
        self.add_loads(conditions, t, 1e-9 * self.options.dt, &mut f);
        Ok(f)
    }

    /// Adds the loads acting at `t` under `conditions` to `f`.
    pub(super) fn add_loads(&self, conditions: &Conditions, t: f64, slack: f64, f: &mut [f64]) {
        for (i, (load, shares)) in self.loads.iter().enumerate() {
            let force = match &conditions.loads {
                Some(l) => l[i],
                None => load.force,
            };
            if !force.active(t, slack) {
                continue;
            }
            for (&v, s) in load.vertices.iter().zip(shares) {
                for d in 0..3 {
                    f[3 * v + d] += s * force.force[d];
                }
            }
        }
    }

    /// The external forces Newton uses: `M g`, or with loads those acting at `t` (refreshed
    /// into the `external` buffer).
    pub(super) fn refresh_external(&mut self, t: f64, slack: f64) {
        if self.loads.is_empty() {
            return;
        }
        let mut f = std::mem::take(&mut self.external);
        f.clear();
        f.extend_from_slice(&self.gravity_forces);
        self.add_loads(&self.conditions, t, slack, &mut f);
        self.external = f;
    }

    /// The external forces of the current Newton solve.
    pub(super) fn external(&self) -> &[f64] {
        if self.loads.is_empty() {
            &self.gravity_forces
        } else {
            &self.external
        }
    }

    /// Gravity forces `M g` (of the active gravity; the loads are in
    /// [`Integrator::external_forces`]).
    pub fn gravity_forces(&self) -> &[f64] {
        &self.gravity_forces
    }

    /// Every constrained vertex with its prescribed position at `t`, in constraint order.
    pub fn constrained_targets(&self, t: f64) -> Vec<(usize, [f64; 3])> {
        let each = |(k, c): (usize, &Constraint)| {
            let motion = self.motion(k);
            let at = move |&i: &usize| (i, motion.position(&self.rest[i], t).into());
            c.vertices.iter().map(at).collect::<Vec<_>>()
        };
        self.constraints.iter().enumerate().flat_map(each).collect()
    }

    /// Sets constrained positions to their targets at `t` and, when `v` is given, the
    /// velocities that reach them from `x_prev` in `dt`.
    pub(super) fn apply_constraints(
        &self,
        x: &mut [f64],
        v: Option<(&mut [f64], &[f64])>,
        t: f64,
        dt: f64,
    ) {
        let mut v = v;
        for (k, c) in self.constraints.iter().enumerate() {
            for &i in &c.vertices {
                let target = self.motion(k).position(&self.rest[i], t);
                if let Some((v, x_prev)) = v.as_mut() {
                    for d in 0..3 {
                        v[3 * i + d] = (target[d] - x_prev[3 * i + d]) / dt;
                    }
                }
                x[3 * i..3 * i + 3].copy_from_slice(target.as_slice());
            }
        }
    }
}

/// Gravity forces `M g`.
pub(super) fn gravity_forces(
    asm: &Assembly,
    mass: &Mass,
    gravity: [f64; 3],
) -> Result<Vec<f64>, AssemblyError> {
    let g: Vec<f64> = (0..asm.num_dofs()).map(|i| gravity[i % 3]).collect();
    let mut f = vec![0.0; g.len()];
    asm.mass_apply(mass, &g, &mut f)?;
    Ok(f)
}

/// Each load with its vertices' shares of its force, in proportion to their masses.
pub(super) fn load_shares(
    asm: &Assembly,
    mass: &Mass,
    loads: Vec<Load>,
) -> Result<Vec<(Load, Vec<f64>)>, IntegratorError> {
    let masses = asm.vertex_masses(mass);
    let mut out = Vec::with_capacity(loads.len());
    for load in loads {
        let invalid = |reason: String| IntegratorError::Invalid {
            field: "loads",
            reason,
        };
        load.force.validate().map_err(invalid)?;
        if let Some(&v) = load.vertices.iter().find(|&&v| v >= masses.len()) {
            return Err(invalid(format!(
                "vertex {v} is out of range for {} vertices",
                masses.len()
            )));
        }
        let total: f64 = load.vertices.iter().map(|&v| masses[v]).sum();
        if !(total > 0.0) {
            return Err(invalid("a load on no vertex (or no mass)".into()));
        }
        let shares = load.vertices.iter().map(|&v| masses[v] / total).collect();
        out.push((load, shares));
    }
    Ok(out)
}

/// Why per-vertex mass scales cannot be used (see [`Integrator::set_mass_scale`]).
pub(super) fn check_mass_scale(scale: &[f64], vertices: usize) -> Result<(), String> {
    if scale.len() != vertices {
        return Err(format!("{} scales for {vertices} vertices", scale.len()));
    }
    match scale.iter().position(|s| !(s.is_finite() && *s > 0.0)) {
        Some(v) => Err(format!("vertex {v}: {} must be finite and > 0", scale[v])),
        None => Ok(()),
    }
}

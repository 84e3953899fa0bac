//! Contact in the Newton loop: the barrier potential of `deform-contact` at Newton's
//! iterates, with its parameters chosen from the mesh and material where a scene does not
//! give them.

use deform_assembly::{Assembly, Outputs, StiffnessMatrix};
use deform_contact::{
    ADAPT_BELOW, ADAPT_MAX, Barrier, ContactHessian, ContactModel, ContactSpec, ContactSummary,
    FrictionLag, MeshObstacle,
};
use deform_mesh::TetMesh;

use crate::IntegratorError;

/// The potential, and what Newton keeps of it between stages.
#[derive(Debug, Clone)]
pub(crate) struct Contact {
    pub(crate) model: ContactModel,
    /// The Hessian's blocks at Newton's iterate (for its matrix).
    pub(crate) hessian: ContactHessian,
    /// Newton's matrix with the Hessian's blocks between vertices (self-contact), on the
    /// union of its pattern and theirs; `None` without such blocks.
    pub(crate) coupled: Option<sprs::CsMat<f64>>,
    /// The potential at the configuration evaluated last: at the end of a step, its state.
    pub(crate) last: Option<ContactSummary>,
    /// Friction lagged at the start of the current Newton solve (empty when static); set
    /// with [`Contact::set_lag`], which clears `secant` with it.
    lag: FrictionLag,
    /// Which pairs of `lag` Newton models with their secant curvature: those one of its
    /// directions carried past their sticking position ([`ContactModel::flag_reversals`]).
    secant: Vec<bool>,
    /// The barrier's stiffness at the start, when it adapts ([`ContactSpec::adaptive_kappa`]).
    pub(crate) adaptive: Option<f64>,
}

impl Contact {
    /// Contact of `mesh`'s surface vertices as `spec` says: `dhat` by default 1e-3 of the
    /// rest bounding box's diagonal (IPC's choice), `kappa` by default such that the
    /// barrier's second derivative at half `dhat` equals the mean diagonal of the rest
    /// stiffness matrix over the surface DOFs, the stiffness with which the material holds a
    /// surface vertex in place. Stiffer barriers settle the gap nearer `dhat`, where the
    /// barrier's curvature changes fastest, and Newton takes more iterations (see
    /// docs/benchmarks.md, "Contact").
    pub(crate) fn build(
        spec: &ContactSpec,
        mesh: &TetMesh,
        asm: &mut Assembly,
    ) -> Result<Self, IntegratorError> {
        let vertices = deform_mesh::topology::surface_vertices(mesh);
        let (lo, hi) = mesh.bounding_box();
        let dhat = spec.dhat.unwrap_or(1e-3 * (hi - lo).norm());
        let invalid = |e: deform_contact::ContactError| IntegratorError::Invalid {
            field: "contact",
            reason: e.to_string(),
        };
        let kappa = match spec.kappa {
            Some(kappa) => kappa,
            None => {
                let unit = Barrier::new(dhat, 1.0);
                let kappa = rest_stiffness(mesh, asm, &vertices)? / unit.second(0.5 * dhat);
                // A dhat far from the mesh's scale over- or underflows the barrier's
                // curvature: say so of dhat, which the user set, not of the kappa derived.
                if !(kappa > 0.0 && kappa.is_finite()) {
                    return Err(invalid(deform_contact::ContactError::Invalid {
                        field: "dhat".into(),
                        reason: format!(
                            "{dhat:e} m leaves no default kappa (derived {kappa:e}) on a body {:.3e} m across: choose dhat nearer that scale, or give kappa",
                            (hi - lo).norm()
                        ),
                    }));
                }
                kappa
            }
        };
        let mut model =
            ContactModel::new(spec.obstacles.clone(), Barrier::new(dhat, kappa), vertices)
                .map_err(invalid)?;
        let rest = mesh.rest_positions_flat();
        if spec.self_contact {
            model = model
                .with_self_contact(deform_mesh::topology::boundary_faces(mesh), &rest)
                .map_err(invalid)?;
        }
        if !spec.meshes.is_empty() {
            let meshes = read_meshes(&spec.meshes)?;
            model = model
                .with_mesh_obstacles(deform_mesh::topology::boundary_faces(mesh), &rest, meshes)
                .map_err(invalid)?;
        }
        // After the meshes: motions and friction's coefficients count them.
        model = model.with_motions(spec.motions.clone()).map_err(invalid)?;
        if let Some(friction) = &spec.friction {
            model = model.with_friction(friction).map_err(invalid)?;
        }
        Ok(Self {
            model,
            hessian: ContactHessian::default(),
            coupled: None,
            last: None,
            lag: FrictionLag::default(),
            secant: Vec::new(),
            adaptive: spec
                .adaptive_kappa
                .unwrap_or(spec.kappa.is_none())
                .then_some(kappa),
        })
    }

    /// After a solve whose last configuration came within [`ADAPT_BELOW`] of `dhat`, doubles
    /// an adaptive barrier's stiffness (up to [`ADAPT_MAX`] times its start).
    pub(crate) fn adapt(&mut self) {
        let (Some(start), Some(last)) = (self.adaptive, self.last) else {
            return;
        };
        let b = self.model.barrier();
        if last.min_distance < ADAPT_BELOW * b.dhat && b.kappa < ADAPT_MAX * start {
            // Doubling a positive finite stiffness stays valid.
            let _ = self
                .model
                .set_stiffness((2.0 * b.kappa).min(ADAPT_MAX * start));
        }
    }

    /// Puts an adaptive barrier's stiffness back to its start.
    pub(crate) fn reset(&mut self) {
        if let Some(start) = self.adaptive {
            let _ = self.model.set_stiffness(start);
        }
    }

    /// The potential at `x`: returns its energy (the barrier's and the lagged friction's),
    /// adds its forces to `forces`, and with `hessian` keeps its blocks.
    pub(crate) fn evaluate(
        &mut self,
        x: &[f64],
        mut forces: Option<&mut [f64]>,
        hessian: bool,
    ) -> Result<f64, deform_contact::ContactError> {
        let mut blocks = hessian.then_some(&mut self.hessian);
        let summary = self
            .model
            .evaluate(x, forces.as_deref_mut(), blocks.as_deref_mut())?;
        self.last = Some(summary);
        let friction = (self.model).add_friction_with(&self.lag, x, forces, blocks, &self.secant);
        Ok(summary.energy + friction)
    }

    /// Lags friction for a solve (no pair flagged yet).
    pub(crate) fn set_lag(&mut self, lag: FrictionLag) {
        self.secant = vec![false; lag.pairs.len()];
        self.lag = lag;
    }

    /// Flags the friction pairs that Newton's displacement `dx` from `x` carries past their
    /// sticking position; from the next Newton matrix on they take their secant curvature.
    pub(crate) fn flag_reversals(&mut self, x: &[f64], dx: &[f64]) {
        (self.model).flag_reversals(&self.lag, x, dx, &mut self.secant);
    }
}

/// The mesh obstacles' surfaces as the contact model takes them (flat positions, moved by
/// their offsets, and triangles).
fn read_meshes(meshes: &[MeshObstacle]) -> Result<Vec<deform_contact::Surface>, IntegratorError> {
    meshes
        .iter()
        .enumerate()
        .map(|(i, m)| {
            // Checked before the file is read: a non-finite offset was reported as a
            // vertex's non-finite coordinate, which the file does not hold.
            if !m.offset.iter().all(|c| c.is_finite()) {
                return Err(IntegratorError::Invalid {
                    field: "contact",
                    reason: format!("meshes[{i}].offset: {:?} must be finite", m.offset),
                });
            }
            let surface =
                deform_mesh::io::read_surface(&m.file).map_err(|e| IntegratorError::Invalid {
                    field: "contact",
                    reason: format!("meshes[{i}]: {e}"),
                })?;
            let offset = nalgebra::Vector3::from(m.offset);
            let flat = surface
                .positions
                .iter()
                .flat_map(|p| {
                    let q = p + offset;
                    [q.x, q.y, q.z]
                })
                .collect();
            Ok((flat, surface.triangles))
        })
        .collect()
}

/// The mean diagonal entry of K at rest over the DOFs of `vertices` (N/m).
fn rest_stiffness(
    mesh: &TetMesh,
    asm: &mut Assembly,
    vertices: &[usize],
) -> Result<f64, IntegratorError> {
    let x: Vec<f64> = mesh
        .rest_positions()
        .iter()
        .flat_map(|p| [p.x, p.y, p.z])
        .collect();
    let mut k: StiffnessMatrix = asm.stiffness_matrix();
    asm.evaluate(
        &x,
        Outputs {
            stiffness: Some(&mut k),
            ..Outputs::default()
        },
    )?;
    let csr = k.csr();
    let mut sum = 0.0;
    for &v in vertices {
        for d in 0..3 {
            sum += csr.get(3 * v + d, 3 * v + d).copied().unwrap_or(0.0);
        }
    }
    Ok(sum / (3 * vertices.len()).max(1) as f64)
}

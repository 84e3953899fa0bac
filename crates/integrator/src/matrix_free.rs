//! The Newton matrix `c_m M + c_k K` as a matrix-free operator: element-by-element force
//! differentials (the seed's Section 1.4) driving the iterative solvers without assembling K.

use deform_assembly::{Assembly, DofMap, ElementTangents, Mass};
use deform_solvers::{LinearOperator, SolverError};
use nalgebra::Matrix3;

/// `y = c_m M x + c_k K x` with `K x` from stored element tangents and the lumped (row-sum)
/// mass, on all `3N` degrees of freedom: the Newton matrix of an unconstrained body, for
/// CG and PCG (Jacobi, block Jacobi) without an assembled K.
pub struct MatrixFreeNewton<'a> {
    tangents: ElementTangents<'a>,
    masses: Vec<f64>,
    c_m: f64,
    c_k: f64,
    /// Contact's Hessian added to the operator, and its factor.
    contact: Option<(&'a deform_contact::ContactHessian, f64)>,
}

impl<'a> MatrixFreeNewton<'a> {
    /// The operator at the configuration of `tangents`.
    pub fn new(
        asm: &Assembly,
        tangents: ElementTangents<'a>,
        mass: &Mass,
        c_m: f64,
        c_k: f64,
    ) -> Self {
        Self {
            tangents,
            masses: asm.vertex_masses(mass),
            c_m,
            c_k,
            contact: None,
        }
    }

    /// The operator plus `scale` times contact's Hessian, its vertex blocks and its blocks
    /// between vertices (nothing without contact).
    pub fn with_contact(
        mut self,
        hessian: Option<&'a deform_contact::ContactHessian>,
        scale: f64,
    ) -> Self {
        self.contact = hessian.map(|h| (h, scale));
        self
    }
}

impl MatrixFreeNewton<'_> {
    /// Contact's vertex blocks with their factor.
    fn vertex_blocks(&self) -> impl Iterator<Item = (usize, &Matrix3<f64>, f64)> {
        let blocks = self.contact.map_or(&[][..], |(h, _)| &h.vertex[..]);
        let scale = self.contact.map_or(0.0, |(_, s)| s);
        blocks.iter().map(move |(v, b)| (*v, b, scale))
    }
}

impl LinearOperator for MatrixFreeNewton<'_> {
    fn nrows(&self) -> usize {
        self.tangents.num_dofs()
    }

    fn apply(&self, x: &[f64], y: &mut [f64]) {
        self.tangents.apply(x, y);
        for (i, yi) in y.iter_mut().enumerate() {
            *yi = self.c_k * *yi + self.c_m * self.masses[i / 3] * x[i];
        }
        if let Some((h, scale)) = self.contact {
            h.add_product(scale, x, y);
        }
    }

    fn diagonal(&self, out: &mut [f64]) {
        self.tangents.diagonal(out);
        for (i, d) in out.iter_mut().enumerate() {
            *d = self.c_k * *d + self.c_m * self.masses[i / 3];
        }
        for (v, b, scale) in self.vertex_blocks() {
            for k in 0..3 {
                out[3 * v + k] += scale * b[(k, k)];
            }
        }
    }

    fn block_diagonal(&self, out: &mut [Matrix3<f64>]) -> Result<(), SolverError> {
        self.tangents.block_diagonal(out);
        for (b, m) in out.iter_mut().zip(&self.masses) {
            *b = *b * self.c_k + Matrix3::identity() * (self.c_m * m);
        }
        for (v, b, scale) in self.vertex_blocks() {
            out[v] += b * scale;
        }
        Ok(())
    }

    fn apply_flops(&self) -> u64 {
        self.tangents.apply_flops()
            + 3 * self.nrows() as u64
            + self
                .contact
                .map_or(0, |(h, _)| 18 * (h.vertex.len() + h.coupling.len()) as u64)
    }
}

/// An operator on all `3N` DOFs restricted to the free ones (`A_ff`): the constrained DOFs
/// of the input are zero, those of the output dropped. Constraints are per vertex, so the
/// free DOFs come in triples and the 3x3 block diagonal restricts block by block.
pub struct Restricted<'a, Op> {
    op: &'a Op,
    dofs: &'a DofMap,
}

impl<'a, Op: LinearOperator> Restricted<'a, Op> {
    /// `op` on the free DOFs of `dofs`.
    pub fn new(op: &'a Op, dofs: &'a DofMap) -> Self {
        Self { op, dofs }
    }
}

impl<Op: LinearOperator> LinearOperator for Restricted<'_, Op> {
    fn nrows(&self) -> usize {
        self.dofs.num_free()
    }

    fn apply(&self, x: &[f64], y: &mut [f64]) {
        let n = self.op.nrows();
        let (mut full_x, mut full_y) = (vec![0.0; n], vec![0.0; n]);
        self.dofs.scatter(x, &mut full_x).expect("sizes match");
        self.op.apply(&full_x, &mut full_y);
        self.dofs.restrict(&full_y, y).expect("sizes match");
    }

    fn diagonal(&self, out: &mut [f64]) {
        let mut full = vec![0.0; self.op.nrows()];
        self.op.diagonal(&mut full);
        self.dofs.restrict(&full, out).expect("sizes match");
    }

    fn block_diagonal(&self, out: &mut [Matrix3<f64>]) -> Result<(), SolverError> {
        let mut full = vec![Matrix3::zeros(); self.op.nrows() / 3];
        self.op.block_diagonal(&mut full)?;
        let constrained = self.dofs.constrained_vertices();
        let free = (0..full.len()).filter(|v| constrained.binary_search(v).is_err());
        for (o, v) in out.iter_mut().zip(free) {
            *o = full[v];
        }
        Ok(())
    }

    fn apply_flops(&self) -> u64 {
        self.op.apply_flops()
    }
}

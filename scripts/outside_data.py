"""Trajectories deform did not make: an independent Backward-Euler Neo-Hookean simulator in
numpy/scipy (its own element math, its own Newton, nothing shared with deform), on a gmsh
mesh, with 1 % Gaussian position noise, written as the `.npy` arrays a user brings, plus the
scene and experiment files that import them (docs/experiments.md, "Your own data").

    pip install "./crates/python[meshio]"   # deform and meshio
    python scripts/outside_data.py OUT [--mesh assets/meshes/torus.msh] [--model stvk]
    cargo xtask experiment OUT/fit.ron --out OUT/fit       # E, nu from the noisy positions
    cargo xtask experiment OUT/select.ron --out OUT/select # which model made the clean ones

    python scripts/outside_data.py OUT --coarsen           # a heterogeneous fine bar instead
    cargo xtask experiment OUT/coarsen.ron --out OUT/coarsen  # a coarse model learns from it

`--coarsen` makes a fine bar (its own structured mesh, 1,920 tets) with a stiff inclusion
(5x the Young's modulus over the middle fifth), six motions under three gravities (two
each: a swing and a spin), a coarse mesh of the same bar that is not nested in the fine one
(168 tets), the embedding of its vertices in the fine mesh (fine element and barycentric
weights), and `coarsen.ron`: deform's `Coarsen` on the imported motions, each with its
gravity, the embedding given, the held-out motions the data's test split. The scene's
material is the bar's bulk (the inclusion unknown to it).

`--model stvk` makes St. Venant-Kirchhoff data instead (use `--speed 0.5`: faster spins
invert elements beyond what its Newton converges through); its swing still inverts elements
(StVK allows it), so model selection leaves out Neo-Hookean, whose energy is undefined
there, saying where.

Needs numpy, scipy and meshio. The truth (E, nu) is written to OUT/truth.txt and is the
scene's material, so the report measures against it; the fit starts from a wrong guess
(`start`: E 1.3e5, nu 0.3), since stage 1 is unusable on noisy positions.
"""

import argparse
import pathlib

import meshio
import numpy as np
import scipy.sparse
import scipy.sparse.linalg

E, NU, RHO, DT, STEPS, TRAJECTORIES = 2e5, 0.35, 1000.0, 0.01, 40, 5
STEPS_COARSEN = 60
E_BAR = 2e6  # the coarsening bar's bulk (its inclusion 5x): it sags about 0.2 m
# Newton's tolerance on the update relative to the velocities (the torus reaches 1e-12; the
# bar's stiff inclusion leaves rounding above that).
TOLERANCE = 1e-12
GRAVITY = np.array([0.0, 0.0, -9.81])
MU = E / (2 * (1 + NU))
LAM = E * NU / ((1 + NU) * (1 - 2 * NU))


def mesh(path):
    m = meshio.read(path)
    x = np.asarray(m.points, dtype=float)
    t = np.asarray(m.cells_dict["tetra"], dtype=np.int64)
    # Positive orientation (deform reorients too, so both see the same corners).
    d = np.einsum("eij->eji", x[t[:, 1:]] - x[t[:, :1]])
    neg = np.linalg.det(d) < 0
    t[neg, 1], t[neg, 2] = t[neg, 2].copy(), t[neg, 1].copy()
    return x, t


class NeoHookean:
    """Psi = mu/2 (|F|^2 - 3) - mu ln J + lambda/2 (ln J)^2 on linear tets."""

    name = "NeoHookean"

    @staticmethod
    def piola(f):
        fit = np.linalg.inv(f).transpose(0, 2, 1)
        lnj = np.log(np.linalg.det(f))
        return MU * (f - fit) + LAM * lnj[:, None, None] * fit

    @staticmethod
    def dpiola(f, df):
        fit = np.linalg.inv(f).transpose(0, 2, 1)
        lnj = np.log(np.linalg.det(f))
        tr = np.einsum("eij,eij->e", fit, df)
        return (
            MU * df
            + (MU - LAM * lnj)[:, None, None] * fit @ df.transpose(0, 2, 1) @ fit
            + LAM * tr[:, None, None] * fit
        )

    def __init__(self, x0, tets):
        self.t = tets
        dm = np.einsum("eij->eji", x0[tets[:, 1:]] - x0[tets[:, :1]])  # columns x_i - x_0
        self.dm_inv = np.linalg.inv(dm)
        self.vol = np.abs(np.linalg.det(dm)) / 6.0
        # Shape-function gradients (4 x 3 per element): grad N_k = row k of Dm^-1 (F = Ds
        # Dm^-1 = sum_k (x_k - x_0) grad N_k^T), grad N_0 = -their sum.
        g = self.dm_inv
        self.grad = np.concatenate([-g.sum(axis=1, keepdims=True), g], axis=1)
        n = len(x0)
        self.n = n
        rows = np.repeat(3 * tets[:, :, None] + np.arange(3), 1, axis=2).reshape(-1, 12)
        self.rows = np.repeat(rows, 12, axis=1).ravel()
        self.cols = np.tile(rows, (1, 12)).ravel()

    def deformation(self, x):
        ds = np.einsum("eij->eji", x[self.t[:, 1:]] - x[self.t[:, :1]])
        return ds @ self.dm_inv

    def forces(self, x):
        p = self.piola(self.deformation(x))
        # f_a = -V P grad_a
        fe = -self.vol[:, None, None] * np.einsum("eij,eaj->eai", p, self.grad)
        out = np.zeros((self.n, 3))
        np.add.at(out, self.t, fe)
        return out

    def stiffness(self, x):
        """K = -df/dx (12 x 12 per element from dP along each node-direction)."""
        f = self.deformation(x)
        ke = np.zeros((len(self.t), 12, 12))
        for b in range(4):
            for d in range(3):
                # dF for a unit move of node b along d: e_d grad_b^T.
                df = np.zeros_like(f)
                df[:, d, :] = self.grad[:, b, :]
                dp = self.dpiola(f, df)
                col = self.vol[:, None, None] * np.einsum("eij,eaj->eai", dp, self.grad)
                ke[:, :, 3 * b + d] = col.reshape(-1, 12)
        k = scipy.sparse.coo_matrix((ke.ravel(), (self.rows, self.cols)), shape=(3 * self.n,) * 2)
        return k.tocsr()


class StVenantKirchhoff(NeoHookean):
    """Psi = mu |E|^2 + lambda/2 (tr E)^2, E = (F^T F - I) / 2."""

    name = "StVenantKirchhoff"

    @staticmethod
    def piola(f):
        e = 0.5 * (f.transpose(0, 2, 1) @ f - np.eye(3))
        tr = np.trace(e, axis1=1, axis2=2)
        return f @ (2 * MU * e + LAM * tr[:, None, None] * np.eye(3))

    @staticmethod
    def dpiola(f, df):
        e = 0.5 * (f.transpose(0, 2, 1) @ f - np.eye(3))
        de = 0.5 * (f.transpose(0, 2, 1) @ df + df.transpose(0, 2, 1) @ f)
        s = 2 * MU * e + LAM * np.trace(e, axis1=1, axis2=2)[:, None, None] * np.eye(3)
        ds = 2 * MU * de + LAM * np.trace(de, axis1=1, axis2=2)[:, None, None] * np.eye(3)
        return df @ s + f @ ds


MODELS = {"neo-hookean": NeoHookean, "stvk": StVenantKirchhoff}


class Heterogeneous(NeoHookean):
    """Neo-Hookean with a Lame pair per element (`mu`, `lam` arrays)."""

    def __init__(self, x0, tets, mu, lam):
        super().__init__(x0, tets)
        self.mu, self.lam = mu[:, None, None], lam[:, None, None]

    def piola(self, f):
        fit = np.linalg.inv(f).transpose(0, 2, 1)
        lnj = np.log(np.linalg.det(f))[:, None, None]
        return self.mu * (f - fit) + self.lam * lnj * fit

    def dpiola(self, f, df):
        fit = np.linalg.inv(f).transpose(0, 2, 1)
        lnj = np.log(np.linalg.det(f))[:, None, None]
        tr = np.einsum("eij,eij->e", fit, df)[:, None, None]
        return self.mu * df + (self.mu - self.lam * lnj) * fit @ df.transpose(0, 2, 1) @ fit + self.lam * tr * fit


def bar(cells, size):
    """A box of `cells` hexahedral cells, each split into six tets around its main diagonal
    (the same split in every cell, so faces match): vertices (V, 3) and tets (T, 4)."""
    nx, ny, nz = cells
    axes = [np.linspace(0.0, s, n + 1) for s, n in zip(size, cells)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    index = lambda i, j, k: (i * (ny + 1) + j) * (nz + 1) + k
    unit = np.eye(3, dtype=int)
    tets = []
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                base = np.array([i, j, k])
                for perm in ([0, 1, 2], [0, 2, 1], [1, 0, 2], [1, 2, 0], [2, 0, 1], [2, 1, 0]):
                    a = base + unit[perm[0]]
                    b = a + unit[perm[1]]
                    corners = [base, a, b, base + 1]
                    tets.append([index(*c) for c in corners])
    tets = np.array(tets, dtype=np.int64)
    d = np.einsum("eij->eji", grid[tets[:, 1:]] - grid[tets[:, :1]])
    neg = np.linalg.det(d) < 0
    tets[neg, 1], tets[neg, 2] = tets[neg, 2].copy(), tets[neg, 1].copy()
    return grid, tets


def embed(x, tets, points):
    """Each point's element in (x, tets) and its barycentric weights there."""
    d = np.einsum("eij->eji", x[tets[:, 1:]] - x[tets[:, :1]])
    inv = np.linalg.inv(d)
    elements, weights = [], []
    for p in points:
        l = np.einsum("eij,ej->ei", inv, p - x[tets[:, 0]])
        w = np.concatenate([1.0 - l.sum(1, keepdims=True), l], 1)
        e = int(np.argmax(w.min(1)))  # the element the point is most inside
        elements.append(e)
        weights.append(w[e])
    return np.array(elements, dtype=np.int64), np.array(weights)


def coarsen_example(out):
    """The heterogeneous fine bar, its six motions under three gravities, the coarse mesh
    and its embedding, and `coarsen.ron` (see the module docs)."""
    global TOLERANCE
    TOLERANCE = 1e-10
    size = (1.0, 0.2, 0.2)
    x0, tets = bar((20, 4, 4), size)
    centroid = x0[tets].mean(1)
    inclusion = np.abs(centroid[:, 0] - 0.5) < 0.1
    young = np.where(inclusion, 5.0 * E_BAR, E_BAR)
    mu = young / (2 * (1 + NU))
    lam = young * NU / ((1 + NU) * (1 - 2 * NU))
    model = Heterogeneous(x0, tets, mu, lam)
    mass = np.zeros(len(x0))
    np.add.at(mass, tets, np.repeat(RHO * model.vol[:, None] / 4, 4, axis=1))
    clamped = np.flatnonzero(x0[:, 0] <= 1e-9)
    free = np.ones(3 * len(x0), dtype=bool)
    free[(3 * clamped[:, None] + np.arange(3)).ravel()] = False
    np.save(out / "fine_vertices.npy", x0)
    np.save(out / "fine_tets.npy", tets)
    np.save(out / "clamped.npy", clamped.astype(np.int64))
    cx, ctets = bar((7, 2, 2), size)
    np.save(out / "coarse_vertices.npy", cx)
    np.save(out / "coarse_tets.npy", ctets)
    elements, weights = embed(x0, tets, cx)
    np.save(out / "embedding_elements.npy", elements)
    np.save(out / "embedding_weights.npy", weights)
    gravities = [(0.0, 0.0, -9.81), (0.0, 0.0, 0.0), (0.0, 9.81, 0.0)]
    rng = np.random.default_rng(40)
    entries = []
    for k in range(6):
        g = gravities[k % 3]
        # A swing (uniform velocity) or a spin about the bar's axis, growing along it.
        along = x0[:, 0:1] / size[0]
        if k < 3:
            v = along * rng.normal(size=3) * 1.0
        else:
            w = np.array([rng.normal() * 10.0, 0.0, 0.0])
            v = along * np.cross(w, x0 - np.array([0.0, 0.1, 0.1]))
        v[clamped] = 0.0
        x, frames, velocities = x0.copy(), [x0.copy()], [v.copy()]
        for _ in range(STEPS_COARSEN):
            x, v = step(model, mass, free, x, v, np.array(g))
            frames.append(x.copy())
            velocities.append(v.copy())
        np.save(out / f"motion_{k}_x.npy", np.array(frames))
        np.save(out / f"motion_{k}_v.npy", np.array(velocities))
        conditions = "" if k % 3 == 0 else f", conditions: (gravity: Some(({g[0]}, {g[1]}, {g[2]})))"
        entries.append(
            f'        (positions: "motion_{k}_x.npy", velocities: File("motion_{k}_v.npy"){conditions}),'
        )
        print(f"motion {k} (gravity {g}): max displacement {np.abs(np.array(frames) - x0).max():.3e} m")
    (out / "fine.ron").write_text(
        f"""// The fine bar as deform sees it: the data's mesh and clamp, the bulk material (the
// stiff inclusion over the middle fifth, 5x E, is not in it: the coarse fits find it).
Scene(
    name: "fine_bar",
    mesh: Arrays(vertices: "fine_vertices.npy", tets: "fine_tets.npy"),
    material: NeoHookean(Young(e: {E_BAR}, nu: {NU})),
    density: {RHO},
    constraints: [(select: File("clamped.npy"), motion: Fixed)],
    integrator: (newton: (rel: 1e-8, abs: 1e-12)),
    steps: {STEPS_COARSEN},
)
"""
    )
    listing = "\n".join(entries)
    (out / "coarsen.ron").write_text(
        f"""// A coarse model learns from a heterogeneous fine bar simulated elsewhere: six motions
// under three gravities (the import's, none, sideways), the coarse mesh's embedding in the
// fine one as given, the data's test split held out (no base model of deform's made them).
Experiment(
    name: "outside_coarsen",
    scene: "fine.ron",
    import: (
        dt: {DT},
        gravity: ({GRAVITY[0]}, {GRAVITY[1]}, {GRAVITY[2]}),
        mass: Lumped,
        trajectories: [
{listing}
        ],
        split: (0.5, 0.17),
    ),
    task: Coarsen(
        mesh: Arrays(vertices: "coarse_vertices.npy", tets: "coarse_tets.npy"),
        embedding: (elements: "embedding_elements.npy", weights: "embedding_weights.npy"),
        regions: 7,
        regularisation: [0.0, 1e-3, 1e-2],
        damping: true,
        output_error: (rollout: 20, max_iterations: 50),
    ),
)
"""
    )


def step(model, mass, free, x, v, gravity=GRAVITY):
    """One Backward-Euler step by Newton on v1: M (v1 - v) = dt (f(x + dt v1) + M g)."""
    v1 = v.copy()
    m3 = np.repeat(mass, 3)
    for _ in range(50):
        x1 = x + DT * v1
        r = (m3 * (v1 - v).ravel()) - DT * (model.forces(x1) + mass[:, None] * gravity).ravel()
        a = scipy.sparse.diags(m3) + DT * DT * model.stiffness(x1)
        a = a[free][:, free]
        dv = np.zeros(3 * len(x))
        dv[free] = scipy.sparse.linalg.spsolve(a.tocsc(), -r[free])
        v1 = v1 + dv.reshape(-1, 3)
        # Converged when the update is at rounding level of the velocities.
        if np.linalg.norm(dv) <= TOLERANCE * np.linalg.norm(v1) + 1e-16:
            return x + DT * v1, v1
    raise RuntimeError("Newton did not converge")


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("out", type=pathlib.Path)
    parser.add_argument("--mesh", default="assets/meshes/torus.msh")
    parser.add_argument("--model", choices=sorted(MODELS), default="neo-hookean")
    parser.add_argument("--speed", type=float, default=1.0, help="scale of the initial velocities")
    parser.add_argument("--coarsen", action="store_true", help="the heterogeneous bar for Coarsen")
    args = parser.parse_args()
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    if args.coarsen:
        coarsen_example(out)
        return
    x0, tets = mesh(args.mesh)
    model = MODELS[args.model](x0, tets)
    mass = np.zeros(len(x0))
    np.add.at(mass, tets, np.repeat(RHO * model.vol[:, None] / 4, 4, axis=1))
    # Clamp a patch at the largest x (a ring on a nail; a bar held at one end).
    lo, hi = x0.min(0), x0.max(0)
    clamped = np.flatnonzero(x0[:, 0] >= hi[0] - 0.1 * (hi[0] - lo[0]))
    free = np.ones(3 * len(x0), dtype=bool)
    free[(3 * clamped[:, None] + np.arange(3)).ravel()] = False
    rng = np.random.default_rng(2026)
    centre = x0.mean(0)
    np.save(out / "vertices.npy", x0)
    np.save(out / "tets.npy", tets)
    np.save(out / "clamped.npy", clamped.astype(np.int64))
    entries = []
    for k in range(TRAJECTORIES):
        # Each motion starts from rest shape with a random velocity field: a spin and a swing.
        omega = rng.normal(size=3) * 2.0 * args.speed
        v = np.cross(omega, x0 - centre) + rng.normal(size=3) * 0.3 * args.speed
        v[clamped] = 0.0
        x = x0.copy()
        frames = [x.copy()]
        for _ in range(STEPS):
            x, v = step(model, mass, free, x, v)
            frames.append(x.copy())
        frames = np.array(frames)
        rms = np.sqrt(np.mean((frames - x0) ** 2))
        noisy = frames + 0.01 * rms * rng.normal(size=frames.shape)
        noisy[:, clamped] = frames[:, clamped]
        np.save(out / f"traj_{k}_x.npy", noisy)
        np.save(out / f"traj_{k}_clean_x.npy", frames)
        entries.append(f'        (positions: "traj_{k}_x.npy", velocities: Derived),')
        print(f"trajectory {k}: RMS displacement {rms:.3e} m, max {np.abs(frames - x0).max():.3e} m")
    (out / "truth.txt").write_text(f"E {E}\nnu {NU}\nmu {MU}\nlambda {LAM}\n")
    (out / "model.ron").write_text(
        f"""// The model to learn: the outside data's mesh and clamp; its E and nu are the truth
// (known here, so the report measures against it; the fit never sees it).
Scene(
    name: "outside",
    mesh: Arrays(vertices: "vertices.npy", tets: "tets.npy"),
    material: {model.name}(Young(e: {E}, nu: {NU})),
    density: {RHO},
    constraints: [(select: File("clamped.npy"), motion: Fixed)],
    integrator: (newton: (rel: 1e-10, abs: 1e-12)),
    steps: {STEPS},
)
"""
    )
    listing = "\n".join(entries)
    clean = listing.replace("_x.npy", "_clean_x.npy")
    (out / "select.ron").write_text(
        f"""// The same motions without noise: which of deform's models made them?
Experiment(
    name: "outside_select",
    scene: "model.ron",
    import: (
        dt: {DT},
        gravity: ({GRAVITY[0]}, {GRAVITY[1]}, {GRAVITY[2]}),
        mass: Lumped,
        trajectories: [
{clean}
        ],
        split: (0.6, 0.2),
    ),
    task: SelectModel(members: [LinearElastic, CorotatedLinear, FixedCorotated, StVenantKirchhoff, NeoHookean, StableNeoHookean]),
)
"""
    )
    (out / "fit.ron").write_text(
        f"""// Outside positions with 1 % noise and no velocities: E and nu by output error with the
// rollout starts estimated.
Experiment(
    name: "outside_fit",
    scene: "model.ron",
    import: (
        dt: {DT},
        gravity: ({GRAVITY[0]}, {GRAVITY[1]}, {GRAVITY[2]}),
        mass: Lumped,
        trajectories: [
{listing}
        ],
        split: (0.6, 0.2),
    ),
    task: FitMaterial(
        start: Some(Young(e: 1.3e5, nu: 0.3)),
        output_error: Some((rollout: 10, max_iterations: 150, max_evaluations: 300, starts: Some(()))),
    ),
)
"""
    )


if __name__ == "__main__":
    main()

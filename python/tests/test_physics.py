"""Materials and assembly: derivatives equal finite differences, K is symmetric."""

import numpy as np
import pytest
import scipy.sparse

import deform

RNG = np.random.default_rng(7)


def random_f(n):
    return np.eye(3) + 0.2 * RNG.standard_normal((n, 3, 3))


@pytest.mark.parametrize("model", deform.MODELS)
def test_stress_and_tangent_are_derivatives(model):
    mat = deform.Material(model, E=1e5, nu=0.3)
    f = random_f(4)
    p, t = mat.first_piola(f), mat.tangent(f)
    h = 1e-6
    for i in range(3):
        for j in range(3):
            d = np.zeros((3, 3))
            d[i, j] = h
            dpsi = (mat.psi(f + d) - mat.psi(f - d)) / (2 * h)
            assert np.allclose(p[:, i, j], dpsi, rtol=1e-5, atol=1e-3)
            # Row-major flattening: T[n, 3i+j, 3k+l] = dP_ij / dF_kl.
            dp = (mat.first_piola(f + d) - mat.first_piola(f - d)) / (2 * h)
            assert np.allclose(t[:, :, 3 * i + j], dp.reshape(-1, 9), rtol=1e-5, atol=1e-2)


def test_projected_tangent_is_positive_semidefinite():
    mat = deform.Material("neo_hookean", E=1e5, nu=0.45)
    t = mat.tangent(random_f(8) * 0.6, project=True)
    assert np.allclose(t, np.transpose(t, (0, 2, 1)))
    assert (np.linalg.eigvalsh(t).min(axis=1) > -1e-6 * np.abs(t).max()).all()


def test_lame_and_ron():
    mat = deform.Material("stvk", mu=2.0, lam=3.0)
    assert mat.lame == (2.0, 3.0)
    again = deform.Material.from_ron(mat.to_ron())
    assert again.lame == (2.0, 3.0)
    with pytest.raises(deform.MaterialError, match="unknown model"):
        deform.Material("rubber", E=1.0, nu=0.3)
    with pytest.raises(deform.MaterialError):
        deform.Material("stvk", E=1.0, nu=0.5)
    with pytest.raises(deform.MaterialError, match="E and nu"):
        deform.Material("stvk", E=1.0)


def test_forces_are_minus_the_energy_gradient_and_k_their_jacobian(small_beam):
    asm = deform.Assembly(small_beam, deform.Material("neo_hookean", E=1e5, nu=0.4))
    x = small_beam.vertices + 0.01 * RNG.standard_normal(small_beam.vertices.shape)
    f = asm.forces(x)
    assert f.shape == x.shape
    k = asm.stiffness(x)
    assert isinstance(k, scipy.sparse.csr_matrix) and k.shape == (x.size, x.size)
    assert abs(k - k.T).max() <= 1e-12 * abs(k).max()
    h = 1e-6
    for i in RNG.choice(x.size, 6, replace=False):
        d = np.zeros(x.size)
        d[i] = h
        d = d.reshape(x.shape)
        de = (asm.energy(x + d) - asm.energy(x - d)) / (2 * h)
        assert np.isclose(-f.reshape(-1)[i], de, rtol=1e-6, atol=1e-6)
        df = (asm.forces(x + d) - asm.forces(x - d)).reshape(-1) / (2 * h)
        assert np.allclose(-k[:, i].toarray().ravel(), df, rtol=1e-5, atol=1e-4)
    # The flat layout gives the same; so does the one-pass evaluation, bit for bit.
    assert np.array_equal(asm.forces(x.reshape(-1)), f.reshape(-1))
    e1, f1, k1 = asm.evaluate(x)
    assert e1 == asm.energy(x) and np.array_equal(f1, f) and (k1 != k).nnz == 0


def test_mass_matrices_carry_the_mass(small_beam):
    asm = deform.Assembly(small_beam, deform.Material("linear", E=1e5, nu=0.3))
    for lumped in (True, False):
        m = asm.mass_matrix(1000.0, lumped=lumped)
        ones = np.tile([1.0, 0.0, 0.0], small_beam.num_vertices)
        assert np.isclose(ones @ (m @ ones), 62.5)
    assert np.isclose(asm.lumped_mass(1000.0).sum(), 62.5)
    with pytest.raises(deform.AssemblyError, match="density"):
        asm.lumped_mass(-1.0)


def test_bad_positions_raise(small_beam):
    asm = deform.Assembly(small_beam, deform.Material("neo_hookean", E=1e5, nu=0.4))
    with pytest.raises(deform.AssemblyError):
        asm.energy(small_beam.vertices[:-1])
    x = small_beam.vertices.copy()
    x[3, 1] = np.nan
    with pytest.raises(deform.AssemblyError):
        asm.forces(x)
    # Inverted: every vertex mirrored.
    with pytest.raises(deform.AssemblyError):
        asm.energy(-small_beam.vertices)

"""deform: deformable elastic solids with the finite element method, made better with data.

Rust does the work; numpy arrays go in and out, sparse matrices come out as
``scipy.sparse.csr_matrix``, reports as plain Python data. Errors are exceptions carrying
deform's message (``MeshError``, ``SceneError``, ... subclass ``ValueError``; a failed step is a
``SimulationError``, a ``RuntimeError``; an unreadable file an ``OSError``). The GIL is
released during assembly, steps and experiments, so Python threads can simulate side by side.

    import deform
    mesh = deform.beam(2)
    nh = deform.Material("neo_hookean", E=1e5, nu=0.4)
    K = deform.Assembly(mesh, nh).stiffness(mesh.vertices)   # scipy CSR, 3V x 3V
"""

from ._deform import (  # noqa: F401
    Assembly,
    AssemblyError,
    Dataset,
    Experiment,
    LearnError,
    LearnedPolicy,
    Material,
    MaterialError,
    Mesh,
    MeshError,
    Scene,
    SceneError,
    Simulation,
    SimulationError,
    SolverData,
    Trajectory,
    beam,
    box_mesh,
    fit_ensemble,
    fit_material,
    read_mesh,
)

MODELS = (
    "linear",
    "corotated",
    "fixed_corotated",
    "stvk",
    "neo_hookean",
    "stable_neo_hookean",
)

__all__ = [
    "Assembly",
    "AssemblyError",
    "Dataset",
    "Experiment",
    "LearnError",
    "LearnedPolicy",
    "MODELS",
    "Material",
    "MaterialError",
    "Mesh",
    "MeshError",
    "Scene",
    "SceneError",
    "Simulation",
    "SimulationError",
    "SolverData",
    "Trajectory",
    "beam",
    "box_mesh",
    "fit_ensemble",
    "fit_material",
    "read_mesh",
]

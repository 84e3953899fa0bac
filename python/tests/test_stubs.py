"""The type stubs describe the module: every public name and method of `deform._deform`
is in `_deform.pyi` and every stub names something that exists."""

import ast
import inspect
import pathlib

import deform
from deform import _deform


def stub_names():
    path = pathlib.Path(deform.__file__).with_name("_deform.pyi")
    tree = ast.parse(path.read_text())
    names = {}
    for node in tree.body:
        if isinstance(node, ast.FunctionDef):
            names[node.name] = None
        elif isinstance(node, ast.ClassDef):
            members = set()
            for item in node.body:
                if isinstance(item, ast.FunctionDef):
                    members.add(item.name)
                elif isinstance(item, ast.AnnAssign):
                    members.add(item.target.id)
            names[node.name] = members
    return names


def public(obj):
    return {n for n in dir(obj) if not n.startswith("_")}


def test_stubs_match_the_module():
    stubs = stub_names()
    assert set(stubs) == public(_deform)
    for name, members in stubs.items():
        obj = getattr(_deform, name)
        if members is None:
            assert callable(obj), name
        elif issubclass(obj, Exception):
            assert members == set(), name
        else:
            assert public(obj) == {m for m in members if not m.startswith("_")}, name
    assert set(deform.__all__) - {"MODELS"} == public(_deform)
    assert all(inspect.getdoc(getattr(_deform, n)) for n in public(_deform))

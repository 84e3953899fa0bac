"""Shared fixtures: the repository's assets and a small beam."""

import pathlib

import pytest

import deform

ROOT = pathlib.Path(__file__).resolve().parents[2]


@pytest.fixture
def assets():
    return ROOT / "assets"


@pytest.fixture
def small_beam():
    return deform.beam(1)

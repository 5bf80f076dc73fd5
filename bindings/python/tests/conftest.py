"""Shared fixtures of the pir2 Python tests."""

import json
import pathlib

import pytest

HERE = pathlib.Path(__file__).parent


@pytest.fixture(scope="session")
def golden():
    """The golden draws written by the pure-Rust test `tests/tests/python_golden.rs`."""
    return json.loads((HERE / "golden_draws.json").read_text())

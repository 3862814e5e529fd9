"""Shared fixtures. Every test runs on Warp's CPU device."""

import os

import numpy as np
import pytest
import warp as wp

wp.config.log_level = wp.LOG_ERROR  # no init banner or module-load lines
wp.init()

DATA = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data"))


def data_case(name):
    """Paths of a sample case in ../shared/data, or skip with the reason."""
    folder = os.path.join(DATA, name)
    labels = os.path.join(folder, "labels.nii.gz")
    if not os.path.exists(labels):
        pytest.skip(f"sample data {folder} is absent (it lives in ../shared/data beside the checkout)")
    return labels, os.path.join(folder, "image.nii.gz")


@pytest.fixture(scope="session")
def tiny_case():
    from warpmpm.phantom import make_phantom

    return make_phantom(seed=0, resolution=3.0)


@pytest.fixture(scope="session")
def tiny_model(tiny_case):
    from warpmpm.model import build_model

    return build_model(tiny_case, "psdl")


@pytest.fixture
def rng():
    return np.random.default_rng(0)

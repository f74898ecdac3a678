"""Shared helpers of the OpenVLA-OFT tests: the tiny checkpoint of ``tests/fixtures/vla_oft/``,
written by OFT's reference code (``tests/fixtures/vla_oft/make_fixtures.py``)."""

import json
from functools import lru_cache
from pathlib import Path

from safetensors.torch import load_file

from infinirl.models.vla.openvla_oft import load_openvla_oft, read_architecture

FIXTURES = Path(__file__).resolve().parents[2] / "fixtures" / "vla_oft"
FOLDER = FIXTURES / "openvla_oft"
ARCHITECTURE = FIXTURES / "architecture.json"
PI0_FOLDER = Path(__file__).resolve().parents[2] / "fixtures" / "vla" / "pi0"


def inputs() -> dict:
    return json.loads((FOLDER / "inputs.json").read_text())


def load(folder=FOLDER, **kwargs):
    options = dict(unnorm_key=inputs()["unnorm_key"], num_images=2, vision=read_architecture(ARCHITECTURE))
    options.update(kwargs)
    return load_openvla_oft(folder, **options)


@lru_cache(maxsize=None)
def reference() -> dict:
    return load_file(str(FOLDER / "reference.safetensors"))


def cameras() -> list:
    images = reference()["raw.images"]
    return [images[:, c].clone() for c in range(images.shape[1])]

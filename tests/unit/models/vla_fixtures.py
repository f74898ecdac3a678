"""Shared helpers of the VLA tests: the tiny fixture checkpoints of ``tests/fixtures/vla/``.

The checkpoints and ``reference.safetensors`` were written by LeRobot 0.4.4 itself
(``tests/fixtures/vla/make_fixtures.py``); ``architecture.json`` holds their tiny sizes.
"""

import json
from functools import lru_cache
from pathlib import Path

from safetensors.torch import load_file

from infinirl.models.vla import VLAArchitecture, load_vla

FIXTURES = Path(__file__).resolve().parents[2] / "fixtures" / "vla"
FAMILIES = ("pi0", "pi05")
TOKENIZER = FIXTURES / "tokenizer"


def architecture() -> VLAArchitecture:
    return VLAArchitecture.from_json(FIXTURES / "architecture.json")


def load(family: str, **kwargs):
    options = dict(architecture=architecture(), tokenizer=TOKENIZER)
    options.update(kwargs)
    return load_vla(FIXTURES / family, **options)


@lru_cache(maxsize=None)
def reference(family: str) -> dict:
    return load_file(str(FIXTURES / family / "reference.safetensors"))


def raw_observation(family: str) -> dict:
    """The reference's raw inputs as a LeRobot-style observation (two of three cameras)."""
    ref = reference(family)
    observation = {key[len("raw."):]: value.clone() for key, value in ref.items()
                   if key.startswith("raw.observation")}
    observation["task"] = json.loads((FIXTURES / family / "inputs.json").read_text())["tasks"]
    return observation

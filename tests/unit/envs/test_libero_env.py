"""LIBERO: without its hub-downloaded assets the adapter must say exactly what is missing where."""

import numpy as np
import pytest

from infinirl.envs import make_env

pytest.importorskip(
    "libero", reason="LIBERO not installed: pip install libero torch==2.13.0 torchvision==0.28.0"
)

from infinirl.envs.libero_env import LiberoAssetsMissing, asset_locations, find_assets  # noqa: E402


def _assets_or_none():
    try:
        return find_assets()
    except LiberoAssetsMissing:
        return None


def test_missing_assets_fail_early_naming_the_paths():
    if _assets_or_none() is not None:
        pytest.skip("LIBERO assets are installed here; nothing is missing")
    with pytest.raises(LiberoAssetsMissing) as error:
        make_env("libero:libero_spatial", 1, num_workers=0)
    for location in asset_locations():
        assert str(location) in str(error.value)


def test_libero_task_steps_with_language_and_upright_images():
    if _assets_or_none() is None:
        pytest.skip(f"LIBERO assets missing (looked in {', '.join(map(str, asset_locations()))})")
    with make_env("libero:libero_spatial/0", 2, num_workers=0, image_size=64) as env:
        obs = env.reset(state_ids=[0, 0])
        np.testing.assert_array_equal(obs["proprio"][0], obs["proprio"][1])
        assert "bowl" in obs["instruction"][0] and obs["rgb"].shape == (2, 64, 64, 3)
        result = env.step(np.zeros((2, 7), np.float32))
        assert result.obs["proprio"].shape == (2, 8)

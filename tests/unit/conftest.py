"""The unit tier starts no Ray: a test that needs a cluster belongs in tests/integration."""

import pytest


@pytest.fixture(autouse=True)
def _no_ray(monkeypatch):
    import ray

    def refuse(*args, **kwargs):
        raise AssertionError("unit tests run without Ray; move a test that starts a cluster to tests/integration")

    monkeypatch.setattr(ray, "init", refuse)

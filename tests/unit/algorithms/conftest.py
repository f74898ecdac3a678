"""Shared random inputs for the algorithm tests: ragged token masks in the aligned layout."""

import pytest
import torch


def make_response_mask(
    generator: torch.Generator, batch: int, width: int, *, empty_rows: int = 0
) -> torch.Tensor:
    """A float64 ``[batch, width]`` response mask: each row is a prompt of 1..3 tokens, a response
    of random length (at least 1 token unless among the ``empty_rows`` first rows), then padding."""
    mask = torch.zeros(batch, width, dtype=torch.float64)
    for row in range(batch):
        prompt = int(torch.randint(1, 4, (1,), generator=generator))
        longest = width - prompt
        drawn = int(torch.randint(1, longest + 1, (1,), generator=generator))
        response = 0 if row < empty_rows else drawn
        mask[row, prompt : prompt + response] = 1.0
    permutation = torch.randperm(batch, generator=generator)
    return mask[permutation]


@pytest.fixture(scope="session")
def response_mask_factory():
    return make_response_mask


"""Frames reassemble from any split; episodes and weights survive encode/decode within the stated
tolerance (checked against float64 references); a weight delta against the wrong base is refused."""

import numpy as np
import pytest

from infinirl.edge.codec import (
    FrameOptions,
    HeldWeights,
    WeightBaseError,
    decode_episode,
    decode_weights,
    encode_episode,
    encode_weights,
    weights_header,
)
from infinirl.edge.frames import FrameError, FrameReader, encode_frame


def test_frames_reassemble_from_arbitrary_pieces():
    messages = [("episodes", b"a" * 70_000), ("weights", b""), ("x", bytes(range(256)))]
    wire = b"".join(encode_frame(s, p) for s, p in messages)
    rng = np.random.default_rng(0)
    reader, got, offset = FrameReader(), [], 0
    while offset < len(wire):
        step = int(rng.integers(1, 5000))
        got += reader.feed(wire[offset:offset + step])
        offset += step
    assert got == messages and reader.buffered == 0


def test_a_foreign_protocol_is_a_frame_error():
    with pytest.raises(FrameError, match="does not speak"):
        FrameReader().feed(b"\x00GET / HTTP/1.1\r\n")


def camera_frames(steps, size=96, seed=0):
    """Smooth images with edges and mild noise, like a camera's view of a table."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size] / size
    frames = []
    for t in range(steps):
        base = np.stack([128 + 80 * np.sin(6 * x + t * 0.1), 128 + 60 * np.cos(5 * y),
                         100 + 100 * (x > 0.5 + 0.01 * t)], axis=-1)
        frames.append(np.clip(base + rng.normal(0, 3, base.shape), 0, 255).astype(np.uint8))
    return np.stack(frames)


def an_episode(steps=12, seed=0):
    rng = np.random.default_rng(seed)
    return {"state": rng.normal(size=(steps + 1, 9)).astype(np.float32),
            "pixels.corner": camera_frames(steps + 1, seed=seed),
            "action": rng.uniform(-1, 1, (steps, 4)).astype(np.float32),
            "reward": rng.normal(size=steps).astype(np.float32),
            "terminated": np.zeros(steps, np.float32), "version": np.arange(steps, dtype=np.int64)}


def test_episode_png_is_exact_and_jpeg_within_tolerance():
    episode = an_episode()
    for options in (FrameOptions(format="png"), FrameOptions(format="jpeg", quality=90)):
        payload = encode_episode(episode, episode_id="edge-0-x-3", frames=options)
        episode_id, decoded = decode_episode(payload)
        assert episode_id == "edge-0-x-3" and set(decoded) == set(episode)
        for name in ("state", "action", "reward", "terminated", "version"):
            assert decoded[name].dtype == episode[name].dtype and np.array_equal(decoded[name], episode[name])
        error = np.abs(decoded["pixels.corner"].astype(np.float64) - episode["pixels.corner"].astype(np.float64))
        if options.format == "png":
            assert error.max() == 0
        else:
            assert error.mean() <= 3.0  # the bound codec's docstring states
            assert len(payload) < episode["pixels.corner"].nbytes / 4


def test_frames_are_resized_to_the_training_resolution():
    episode = an_episode(steps=3)
    _, decoded = decode_episode(encode_episode(episode, episode_id="e", frames=FrameOptions(size=(48, 64))))
    assert decoded["pixels.corner"].shape == (4, 48, 64, 3)


def weights(seed=0):
    rng = np.random.default_rng(seed)
    return {"layer.weight": rng.normal(0, 0.1, (64, 32)).astype(np.float32),
            "layer.bias": rng.normal(0, 0.1, 64).astype(np.float32), "steps": np.array([7], np.int64)}


def test_full_push_is_exact():
    payload, held = encode_weights(weights(), 1)
    assert weights_header(payload)["kind"] == "full"
    decoded = decode_weights(payload, None)
    assert decoded.digest == held.digest and decoded.version == 1
    for name, array in weights().items():
        assert np.array_equal(decoded.tensors[name], array)


def test_delta_push_within_the_stated_bound_and_without_drift():
    rng = np.random.default_rng(1)
    current = weights()
    payload, held_cloud = encode_weights(current, 0)
    held_edge = decode_weights(payload, None)
    for version in range(1, 6):  # small SGD-like steps
        current = {n: (a + rng.normal(0, 1e-3, a.shape).astype(np.float32) if a.dtype == np.float32 else a + 1)
                   for n, a in current.items()}
        payload, held_cloud = encode_weights(current, version, held_cloud)
        assert weights_header(payload)["kind"] == "delta"
        previous = held_edge
        held_edge = decode_weights(payload, held_edge)
        assert held_edge.digest == held_cloud.digest  # both ends hold the same bits: no drift
        for name, array in current.items():
            exact = array.astype(np.float64)
            got = held_edge.tensors[name].astype(np.float64)
            if array.dtype != np.float32:
                assert np.array_equal(got, exact)
                continue
            delta = np.abs(exact - previous.tensors[name].astype(np.float64))
            bound = delta * 2.0**-11 + 2.0**-24 + np.abs(exact) * 2.0**-23
            assert np.all(np.abs(got - exact) <= bound), name


def test_delta_against_the_wrong_base_is_refused():
    first, held1 = encode_weights(weights(0), 1)
    _, held2 = encode_weights(weights(1), 2, held1)
    delta, _ = encode_weights({n: a + 1e-3 if a.dtype == np.float32 else a for n, a in weights(1).items()}, 3, held2)
    assert weights_header(delta)["kind"] == "delta"
    with pytest.raises(WeightBaseError, match="base version 2"):
        decode_weights(delta, decode_weights(first, None))  # the edge holds version 1
    with pytest.raises(WeightBaseError, match="holds no weights"):
        decode_weights(delta, None)
    tampered = HeldWeights.of(2, {n: a.copy() for n, a in held2.tensors.items()})
    tampered.tensors["layer.bias"][0] += 1.0
    with pytest.raises(WeightBaseError):
        decode_weights(delta, HeldWeights(version=2, tensors=tampered.tensors, digest="0" * 64))


def test_full_when_a_delta_does_not_pay():
    _, held = encode_weights(weights(0), 1)
    unrelated = {n: a * 1e6 if a.dtype == np.float32 else a for n, a in weights(5).items()}  # beyond float16
    payload, _ = encode_weights(unrelated, 2, held)
    assert weights_header(payload)["kind"] == "full"

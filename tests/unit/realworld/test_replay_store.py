"""The persistent replay store: round trip, batch contents, uniform seeded sampling, exact resume,
eviction by disk bound, the byte-bounded cache, and one-line errors for bad input."""

import os
import shutil

import numpy as np
import pytest

from infinirl.realworld.replay import ByteLRU, EpisodeSpec, ReplayStore, SamplingSpec, StoreOptions
from tests.unit.realworld.replay_fixtures import SPEC, check_batch, make_episode

FAST = {"durable": False}  # fsync is exercised by the crash tests; here it only slows the suite


def fill(path, n, start=0, sampling=None, **options):
    store = ReplayStore(str(path), SPEC, options=StoreOptions(**{**FAST, **options}), sampling=sampling)
    for i in range(start, start + n):
        assert store.append(make_episode(i)) == i
    return store


def assert_episode_equal(got, want):
    assert set(got) == set(want)
    for name in want:
        np.testing.assert_array_equal(got[name], want[name], err_msg=name)
        assert got[name].dtype == want[name].dtype


def test_round_trip_across_segments_and_reopen(tmp_path):
    store = fill(tmp_path, 30, segment_bytes=3000)
    total = sum(len(make_episode(i)["step"]) for i in range(30))
    assert len(store) == total and store.num_episodes == 30 and len(store.segments) > 3
    for i in range(30):
        assert_episode_equal(store.episode(i), make_episode(i))
    store.close()
    with ReplayStore(str(tmp_path), options=StoreOptions(**FAST)) as again:  # the spec comes from store.json
        assert again.spec == SPEC and len(again) == total and again.next_episode_id == 30
        for i in range(30):
            assert_episode_equal(again.episode(i), make_episode(i))
        appended = make_episode(30)
        again.append(appended)
        for array in appended.values():
            array[...] = 0  # the caller reuses its arrays: the store kept its own copy
        assert_episode_equal(again.episode(30), make_episode(30))
        check_batch(again.gather(np.arange(len(again) - 5, len(again))))
        with pytest.raises(IndexError, match=rf"live range \[0, {len(again)}\)"):
            again.gather(np.array([len(again)]))
        again.verify()


def test_batches_pair_each_observation_with_the_next_one_of_the_same_episode(tmp_path):
    with fill(tmp_path, 25, segment_bytes=2500, cache_bytes=6000) as store:
        assert store.cache.keys() and len(store.cache) < len(store.segments)  # cached and mapped segments both
        for _ in range(20):
            batch = store.sample(64)
            assert list(batch) == SPEC.batch_keys()
            check_batch(batch)


def test_sampling_is_uniform_over_all_transitions_and_seeded(tmp_path):
    with fill(tmp_path, 40, segment_bytes=3000) as store:
        n, draws = len(store), 400 * 256
        counts = np.zeros(n)
        for _ in range(400):
            np.add.at(counts, store.sample_positions(256), 1)
        expected = draws / n
        chi2 = ((counts - expected) ** 2 / expected).sum()
        assert chi2 < (n - 1) + 6 * np.sqrt(2 * (n - 1)), chi2  # ~6 sigma above the chi-square mean
    a = ReplayStore(str(tmp_path), sampling=SamplingSpec(seed=5), writable=False)
    b = ReplayStore(str(tmp_path), sampling=SamplingSpec(seed=5), writable=False)
    c = ReplayStore(str(tmp_path), sampling=SamplingSpec(seed=6), writable=False)
    first = a.sample_positions(128)
    np.testing.assert_array_equal(first, b.sample_positions(128))
    assert not np.array_equal(first, c.sample_positions(128))


def test_recent_weighting_draws_the_declared_share_from_the_newest_transitions(tmp_path):
    fill(tmp_path, 40).close()
    sampling = SamplingSpec(seed=1, recent_fraction=0.5, recent_transitions=20)
    with ReplayStore(str(tmp_path), writable=False, sampling=sampling) as store:
        n = len(store)
        positions = np.concatenate([store.sample_positions(256) for _ in range(200)])
        in_window = np.mean(positions >= n - 20)
        want = 0.5 + 0.5 * 20 / n
        assert abs(in_window - want) < 0.01, (in_window, want)  # std ~0.0015


def test_state_dict_resumes_the_exact_stream_of_batches(tmp_path):
    original = fill(tmp_path / "a", 20, sampling=SamplingSpec(seed=3), segment_bytes=3000)
    for _ in range(5):
        original.sample(32)
    state = original.state_dict()
    shutil.copytree(tmp_path / "a", tmp_path / "b")  # the store as it was when the state was taken
    expected = [original.sample(32) for _ in range(3)]
    original.append(make_episode(20))  # appends after the resume point must be replayed too
    expected.append(original.sample(32))
    original.close()
    with ReplayStore(str(tmp_path / "b"), sampling=SamplingSpec(seed=99), options=StoreOptions(**FAST)) as resumed:
        resumed.load_state_dict(state)
        got = [resumed.sample(32) for _ in range(3)]
        resumed.append(make_episode(20))
        got.append(resumed.sample(32))
    for a, b in zip(expected, got):
        for key in a:
            np.testing.assert_array_equal(a[key], b[key])
    fresh = ReplayStore(str(tmp_path / "c"), SPEC, options=StoreOptions(**FAST))
    with pytest.raises(ValueError, match="taken with 20 episodes committed, the store holds 0"):
        fresh.load_state_dict(state)


def test_disk_bound_evicts_the_oldest_segments(tmp_path):
    segment_bytes, max_bytes = 3000, 12000
    store = fill(tmp_path, 80, segment_bytes=segment_bytes, max_bytes=max_bytes)
    assert store.disk_bytes <= max_bytes + 2 * (segment_bytes + 1000)
    on_disk = sorted(os.listdir(tmp_path / "segments"))
    assert on_disk == [f"{n:08d}" for n in sorted(store.segments)] and on_disk[0] != "00000000"
    first = int(store.table.column("first_position")[0])
    oldest = store.segments[min(store.segments)].episode_ids[0]
    with pytest.raises(KeyError, match="episode 0 is not in the replay store"):
        store.episode(0)
    for _ in range(20):
        batch = store.sample(64)
        check_batch(batch)
        assert batch["episode"].min() >= oldest
    assert store.sample_positions(1000).min() >= first
    live = (len(store), store.num_episodes)
    store.close()
    with ReplayStore(str(tmp_path), options=StoreOptions(**FAST, max_bytes=max_bytes)) as again:
        assert (len(again), again.num_episodes, again.next_episode_id) == (*live, 80)
        assert_episode_equal(again.episode(79), make_episode(79))


def test_byte_lru_evicts_least_recently_used_and_stays_within_its_bytes():
    cache = ByteLRU(10)
    for key in "abc":
        assert cache.put(key, key.upper(), 4)
        assert cache.nbytes <= 10
    assert cache.keys() == ["b", "c"]  # a was least recently used
    assert cache.get("b") == "B"  # b is now the most recent
    cache.put("d", "D", 4)
    assert cache.keys() == ["b", "d"] and cache.nbytes == 8
    assert not cache.put("huge", "X", 11) and "huge" not in cache and cache.nbytes == 8
    with pytest.raises(ValueError, match="cache capacity must be >= 0"):
        ByteLRU(-1)


def test_store_cache_holds_the_newest_segments_within_its_bytes_and_changes_no_batch(tmp_path):
    limit = 7000
    cached = ReplayStore(str(tmp_path / "a"), SPEC, options=StoreOptions(**FAST, segment_bytes=2500, cache_bytes=limit),
                         sampling=SamplingSpec(seed=4))
    uncached = ReplayStore(str(tmp_path / "b"), SPEC, options=StoreOptions(**FAST, segment_bytes=2500, cache_bytes=0),
                           sampling=SamplingSpec(seed=4))
    for i in range(40):
        cached.append(make_episode(i))
        uncached.append(make_episode(i))
        assert cached.cache.nbytes <= limit
        batch, other = cached.sample(16), uncached.sample(16)
        for key in batch:
            np.testing.assert_array_equal(batch[key], other[key])
    newest = sorted(cached.segments)  # the open segment included
    assert sorted(cached.cache.keys()) == newest[-len(cached.cache):] and len(cached.cache) >= 2
    assert len(uncached.cache) == 0
    cached.close()
    uncached.close()


@pytest.mark.parametrize("field, value, message", [
    ("pixels", np.zeros((6, 6, 5, 3), np.uint8), r"observation field 'pixels': expected shape \(6, 6, 6, 3\)"),
    ("pixels", np.zeros((7, 6, 6, 3), np.uint8), r"fields \['pixels'\] disagree on the number of steps"),
    ("state", np.zeros((6, 3), np.float64), r"observation field 'state': expected dtype float32, got float64"),
    ("action", np.zeros((5, 3), np.float32), r"step field 'action': expected shape \(5, 2\) \(5 rows for 5 steps\)"),
    ("action", np.zeros((4, 2), np.float32), r"fields \['action'\] disagree on the number of steps"),
    ("reward", np.zeros(5, np.int32), r"step field 'reward': expected dtype float32, got int32; cast it"),
])
def test_bad_episodes_get_one_line_errors_naming_the_field(tmp_path, field, value, message):
    episode = make_episode(1)  # 5 steps
    assert len(episode["step"]) == 5
    episode[field] = value
    with ReplayStore(str(tmp_path), SPEC, options=StoreOptions(**FAST)) as store:
        with pytest.raises(ValueError, match=message) as info:
            store.append(episode)
        assert "\n" not in str(info.value)
        assert store.num_episodes == 0 and not any(s.num_episodes for s in store.segments.values())
        del episode[field]
        with pytest.raises(ValueError, match=rf"missing \['{field}'\]"):
            store.append(episode)


def test_bad_specs_and_options_are_refused(tmp_path):
    with pytest.raises(ValueError, match="field 'a/b': names may hold"):
        EpisodeSpec(observations={"a/b": ((1,), "float32")})
    with pytest.raises(ValueError, match=r"\['x'\] are declared both"):
        EpisodeSpec(observations={"x": ((1,), "float32")}, steps={"x": ((), "float32")})
    with pytest.raises(ValueError, match="recent_transitions must be >= 1"):
        SamplingSpec(recent_fraction=0.5)
    with pytest.raises(ValueError, match="segment_bytes must be >= 1"):
        StoreOptions(segment_bytes=0)
    with pytest.raises(ValueError, match="creating a replay store needs an EpisodeSpec"):
        ReplayStore(str(tmp_path / "new"))
    with pytest.raises(FileNotFoundError, match="no replay store here"):
        ReplayStore(str(tmp_path / "none"), writable=False)
    fill(tmp_path / "s", 2).close()
    other = EpisodeSpec(observations={"state": ((3,), "float32")})
    with pytest.raises(ValueError, match="store.json: the store holds fields"):
        ReplayStore(str(tmp_path / "s"), other)
    with ReplayStore(str(tmp_path / "s"), writable=False) as reader:
        with pytest.raises(RuntimeError, match="opened with writable=False"):
            reader.append(make_episode(2))
    with ReplayStore(str(tmp_path / "e"), SPEC) as empty:
        with pytest.raises(ValueError, match="cannot sample from an empty replay store"):
            empty.sample(4)

"""Episodes whose every value says which episode and step it is, and a writer process to kill.

``python -m tests.unit.realworld.replay_fixtures DIR SEGMENT_BYTES MAX_BYTES [LIMIT]`` opens the
store at DIR for writing and appends episode after episode (from the store's next episode id on),
printing ``committed <id>`` after each append returns, until LIMIT episodes are in (default: never).
Episode ``i`` is appended with the source id :func:`source_of` ``(i)``.
"""

from __future__ import annotations

import sys

import numpy as np

from infinirl.realworld.replay import EpisodeSpec, ReplayStore, StoreOptions

SPEC = EpisodeSpec(observations={"pixels": ((6, 6, 3), "uint8"), "state": ((3,), "float32")},
                   steps={"action": ((2,), "float32"), "reward": ((), "float32"), "done": ((), "bool"),
                          "episode": ((), "int64"), "step": ((), "int64")})


def steps_of(episode_id: int) -> int:
    return 3 + (episode_id * 7) % 5


def source_of(episode_id: int) -> str:
    return f"src-{episode_id}"


def make_episode(episode_id: int) -> dict[str, np.ndarray]:
    """``state`` row ``t`` is ``[episode, t, episode + t]``; pixels hold ``(episode + t) % 251``."""
    steps = steps_of(episode_id)
    t_obs = np.arange(steps + 1)
    t = np.arange(steps)
    return {
        "pixels": np.broadcast_to(((episode_id + t_obs) % 251).astype(np.uint8)[:, None, None, None],
                                  (steps + 1, 6, 6, 3)).copy(),
        "state": np.stack([np.full(steps + 1, episode_id), t_obs, episode_id + t_obs], axis=1).astype(np.float32),
        "action": np.stack([t * 0.5, -t * 0.5 + episode_id], axis=1).astype(np.float32),
        "reward": (t == steps - 1).astype(np.float32),
        "done": t == steps - 1,
        "episode": np.full(steps, episode_id, np.int64),
        "step": t.astype(np.int64),
    }


def check_batch(batch: dict[str, np.ndarray]) -> None:
    """Every row of a sampled batch is the transition its ``episode``/``step`` fields name."""
    episode, step = batch["episode"], batch["step"]
    np.testing.assert_array_equal(batch["obs.state"][:, 0], episode)
    np.testing.assert_array_equal(batch["obs.state"][:, 1], step)
    np.testing.assert_array_equal(batch["next_obs.state"][:, 0], episode)  # next_obs stays in the episode
    np.testing.assert_array_equal(batch["next_obs.state"][:, 1], step + 1)
    np.testing.assert_array_equal(batch["obs.pixels"][:, 0, 0, 0], (episode + step) % 251)
    np.testing.assert_array_equal(batch["next_obs.pixels"][:, 5, 5, 2], (episode + step + 1) % 251)
    np.testing.assert_array_equal(batch["action"][:, 0], step * 0.5)
    steps = np.array([steps_of(int(e)) for e in episode])
    np.testing.assert_array_equal(batch["done"], step == steps - 1)


def main(argv: list[str]) -> None:
    path, segment_bytes, max_bytes = argv[0], int(argv[1]), int(argv[2])
    limit = int(argv[3]) if len(argv) > 3 else None
    options = StoreOptions(segment_bytes=segment_bytes, max_bytes=max_bytes or None, cache_bytes=segment_bytes * 2)
    with ReplayStore(path, SPEC, options=options) as store:
        print(f"opened {store.next_episode_id}", flush=True)
        while limit is None or store.next_episode_id < limit:
            episode_id = store.append(make_episode(store.next_episode_id), source_id=source_of(store.next_episode_id))
            print(f"committed {episode_id}", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])

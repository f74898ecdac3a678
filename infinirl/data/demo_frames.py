"""Every frame of a LeRobotDataset of demonstrations in memory, and batches of them for cloning.

:class:`DemoFrames` reads a dataset (one camera, ``observation.state``, ``action``, the task's
wording) into tensors once; :meth:`DemoFrames.batch` draws frames with the action chunk that follows
each in its episode. The SFT runner clones on them, and PPO's behaviour-cloning anchor
(``algorithm.bc``) adds their flow-matching loss to the policy's update.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812

from infinirl.config import ConfigError

__all__ = ["CAMERA_PREFIX", "DemoFrames", "random_shift"]

CAMERA_PREFIX = "observation.images."


@dataclass(kw_only=True)
class DemoFrames:
    """Every frame of a dataset in memory: camera images, state, action, and where its episode ends."""

    camera_key: str
    images: torch.Tensor
    """uint8 ``[N, H, W, 3]``."""
    state: torch.Tensor
    action: torch.Tensor
    episode_end: torch.Tensor
    """The (exclusive) index of the last frame of each frame's episode."""
    task_index: torch.Tensor
    tasks: list[str]
    stats: dict[str, dict[str, np.ndarray]]

    @staticmethod
    def camera_of(reader, camera_key: str | None = None) -> str:
        """``camera_key``, or the dataset's only camera; a ConfigError naming data.camera_key otherwise."""
        cameras = [key for key in reader.video_keys if key.startswith(CAMERA_PREFIX)]
        if camera_key is None:
            if len(cameras) != 1:
                raise ConfigError(f"data.camera_key: the dataset at {reader.root} has cameras {cameras}; name one")
            return cameras[0]
        if camera_key not in cameras:
            raise ConfigError(f"data.camera_key={camera_key!r}: the dataset at {reader.root} has cameras {cameras}")
        return camera_key

    @classmethod
    def read(cls, reader, camera_key: str | None = None) -> DemoFrames:
        camera_key = cls.camera_of(reader, camera_key)
        for key in ("observation.state", "action"):
            if key not in reader.features or key not in reader.stats:
                raise ConfigError(f"data.path: the dataset at {reader.root} has no {key!r} (with statistics in "
                                  "meta/stats.json); SFT needs states and actions")
        images, state, action, end, task = [], [], [], [], []
        frames_so_far = 0
        for episode in range(reader.num_episodes):
            frames = reader.episode(episode)
            length = len(frames["action"])
            frames_so_far += length
            images.append(torch.from_numpy(np.array(frames[camera_key])))
            state.append(torch.from_numpy(np.array(frames["observation.state"], dtype=np.float32)))
            action.append(torch.from_numpy(np.array(frames["action"], dtype=np.float32)))
            end.append(torch.full((length,), frames_so_far, dtype=torch.long))
            task.append(torch.from_numpy(np.array(frames["task_index"], dtype=np.int64)))
        return cls(camera_key=camera_key, images=torch.cat(images), state=torch.cat(state), action=torch.cat(action),
                   episode_end=torch.cat(end), task_index=torch.cat(task), tasks=list(reader.tasks),
                   stats=reader.stats)

    def __len__(self) -> int:
        return len(self.action)

    def extended(self, other: DemoFrames) -> DemoFrames:
        """These frames followed by ``other``'s (its episodes and tasks joined to ours by their
        wording); the normalisation statistics stay ours."""
        if other.camera_key != self.camera_key or other.images.shape[1:] != self.images.shape[1:]:
            raise ValueError(f"cannot join frames of {other.camera_key} {tuple(other.images.shape[1:])} to "
                             f"{self.camera_key} {tuple(self.images.shape[1:])}")
        tasks = self.tasks + [task for task in other.tasks if task not in self.tasks]
        remap = torch.tensor([tasks.index(task) for task in other.tasks], dtype=torch.long)
        return DemoFrames(camera_key=self.camera_key, images=torch.cat([self.images, other.images]),
                          state=torch.cat([self.state, other.state]), action=torch.cat([self.action, other.action]),
                          episode_end=torch.cat([self.episode_end, other.episode_end + len(self)]),
                          task_index=torch.cat([self.task_index, remap[other.task_index]]), tasks=tasks,
                          stats=self.stats)

    @property
    def image_size(self) -> int:
        return int(self.images.shape[1])

    def normalization_stats(self, min_std: float) -> dict[str, dict[str, torch.Tensor]]:
        """MEAN_STD statistics of state and action, each std floored at ``min_std``."""
        def vector(key: str, name: str) -> torch.Tensor:
            return torch.as_tensor(self.stats[key][name], dtype=torch.float32).reshape(-1)

        return {key: {"mean": vector(key, "mean"), "std": vector(key, "std").clamp_min(min_std)}
                for key in ("observation.state", "action")}

    def batch(self, indices: torch.Tensor, chunk: int, shift: int = 0,
              generator: torch.Generator | None = None) -> tuple[dict, torch.Tensor, torch.Tensor]:
        """Observations (the dataset's LeRobot keys), action chunks ``[B, chunk, A]`` and their
        validity ``[B, chunk]`` for frames ``indices``; a chunk past its episode's end repeats the
        last action (masked). ``shift``: :func:`random_shift`'s pad, its offsets from ``generator``."""
        steps = indices[:, None] + torch.arange(chunk)[None]
        last = self.episode_end[indices][:, None] - 1
        valid = steps <= last
        actions = self.action[torch.minimum(steps, last)]
        images = self.images[indices].permute(0, 3, 1, 2).float() / 255.0
        if shift:
            images = random_shift(images, shift, generator)
        observation = {self.camera_key: images, "observation.state": self.state[indices],
                       "task": [self.tasks[i] for i in self.task_index[indices].tolist()]}
        return observation, actions, valid


def random_shift(images: torch.Tensor, pad: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """DrQ's augmentation: pad ``[B, C, H, W]`` by replicating the border, crop back at a random
    offset (drawn from ``generator``; None: torch's global generator)."""
    height, width = images.shape[-2:]
    padded = F.pad(images, (pad, pad, pad, pad), mode="replicate")
    offsets = torch.randint(0, 2 * pad + 1, (images.shape[0], 2), generator=generator)
    return torch.stack([padded[i, :, y:y + height, x:x + width] for i, (y, x) in enumerate(offsets.tolist())])

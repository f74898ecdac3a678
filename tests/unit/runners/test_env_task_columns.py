"""Which task every env column of an embodied trajectory runs (``env_task_columns``): the rollout
ranks' envs in rank order, each rank's pipeline stages in order, env ``i`` of a stage running task
``(i // task_block) % tasks`` as the env factories do, so the per-task advantage normalisation
(``algorithm.normalize_advantages_per_task``) groups the right decisions."""

import pytest

pytest.importorskip("metaworld")

from infinirl.config import to_dataclass  # noqa: E402
from infinirl.envs.registry import ENVS  # noqa: E402
from infinirl.runners.embodied import env_task_columns, task_block  # noqa: E402
from infinirl.runners.embodied_config import EmbodiedConfig  # noqa: E402

TASKS = "metaworld:reach-v3,push-v3,door-open-v3"


def cfg(num_envs, stages=1, **algorithm):
    return to_dataclass(EmbodiedConfig, {"env": {"name": TASKS, "num_envs": num_envs}, "rollout_steps": 8,
                                         "rollout": {"pipeline_stages": stages},
                                         "algorithm": {"mini_batches": 2, **algorithm},
                                         "eval": {"video_episodes": 0}})


def factory_tasks(config, sizes, ranks):
    """What the env factory itself gives env ``i`` of every stage, joined in the trajectory's order."""
    factory = ENVS.get("metaworld")(TASKS.partition(":")[2], task_block=task_block(config))
    names = list(factory.tasks)
    return [names.index(factory.task_of(i)) for _ in range(ranks) for size in sizes for i in range(size)]


@pytest.mark.parametrize("num_envs, stages, ranks, algorithm, expected", [
    (6, 1, 1, {}, [0, 1, 2, 0, 1, 2]),
    (8, 2, 1, {}, [0, 1, 2, 0, 0, 1, 2, 0]),          # each stage's envs count from 0 again
    (12, 1, 2, {}, [0, 1, 2, 0, 1, 2] * 2),           # each rollout rank's too
    (12, 1, 2, {"name": "grpo", "group_size": 2}, [0, 0, 1, 1, 2, 2] * 2),  # task blocks of a group
])
def test_columns_follow_the_ranks_and_stages(num_envs, stages, ranks, algorithm, expected):
    config = cfg(num_envs, stages, **algorithm)
    columns, names = env_task_columns(config, ranks)
    assert columns.tolist() == expected
    sizes = [len(expected) // ranks // stages] * stages if num_envs % (ranks * stages) == 0 else None
    assert columns.tolist() == factory_tasks(config, sizes, ranks)
    assert names == ["reach-v3", "push-v3", "door-open-v3"]


def test_one_task_env_has_one_column_label():
    one = to_dataclass(EmbodiedConfig, {"env": {"name": "metaworld:reach-v3", "num_envs": 4},
                                        "eval": {"video_episodes": 0}})
    columns, names = env_task_columns(one, 1)
    assert columns.tolist() == [0, 0, 0, 0] and len(names) == 1

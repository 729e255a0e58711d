"""Every private LeRobot name the plugin uses, in one place.

LeRobot may rename or remove its private names in any release. They were checked against LeRobot
`LEROBOT_VERSION_CHECKED`; `tests/test_lerobot_private.py` fails, naming the installed version, when one of
`PRIVATE_NAMES` has moved. Every other module of the package takes these names from here.

Each name is looked up when it is used, never when this module is imported: a name LeRobot has moved breaks only
the command that needs it, with an ImportError naming the name and both versions (`moved_message`), while the
policy (`--policy.type=ebvla`) and the env types still register.

- `make_vec_env_cls`: LeRobot's choice of vector env class, so that our env configs build the same vector envs
  as LeRobot's own (`EnvConfig.create_envs`).
- `lazy_async_vector_env`: LeRobot's async vector env that starts its worker processes only when a task is
  evaluated, as `lerobot.envs.metaworld` and `lerobot.envs.libero` use.
- `get_libero_suite`, `select_libero_task_ids`: LeRobot's validation of LIBERO suite names and task ids. They
  import `lerobot.envs.libero` when called: it imports the optional `libero` package, which asks questions on
  stdin until LIBERO is set up (`ebvla-install-libero-assets`).
- `POLICY_SERVER_CHUNK_METHOD`: the private method of LeRobot's `PolicyServer` that `EBVLAPolicyServer`
  (serving.py, run by `ebvla-policy-server`) overrides to see every chunk it serves.
- `DATASET_READER_QUERY_METHOD`: the private method of LeRobot's `DatasetReader` that reads a sample's delta rows;
  `pipelines.column_queries` answers it, for one dataset's reader, from the queried column alone.
  `lerobot_reads_single_columns` tells whether the installed LeRobot does so itself (LeRobot PR #4314, after
  0.6.1, which added `DatasetReader._column_view`).
- `TRAIN_DATASETS_FACTORY`: the function `lerobot.scripts.lerobot_train` builds its datasets with; while
  `pipelines.column_queries.single_column_delta_queries` is open, lerobot-train's datasets come through it.
"""

import importlib
import importlib.metadata
from collections.abc import Callable, Iterable
from typing import Any

__all__ = [
    "DATASET_READER_QUERY_METHOD",
    "LEROBOT_VERSION_CHECKED",
    "POLICY_SERVER_CHUNK_METHOD",
    "PRIVATE_NAMES",
    "TRAIN_DATASETS_FACTORY",
    "get_libero_suite",
    "lazy_async_vector_env",
    "lerobot_reads_single_columns",
    "make_vec_env_cls",
    "select_libero_task_ids",
]

# The LeRobot release every name below was checked against (`pip show lerobot`).
LEROBOT_VERSION_CHECKED = "0.6.1"
POLICY_SERVER_CHUNK_METHOD = "_predict_action_chunk"
DATASET_READER_MODULE = "lerobot.datasets.dataset_reader"
DATASET_READER_QUERY_METHOD = "_query_hf_dataset"
# Added by LeRobot PR #4314 together with its own single-column delta queries.
DATASET_READER_COLUMN_VIEW = "_column_view"
TRAIN_MODULE = "lerobot.scripts.lerobot_train"
TRAIN_DATASETS_FACTORY = "make_train_eval_datasets"
LIBERO_MODULE = "lerobot.envs.libero"
# (module, attribute) of every private LeRobot name above; attributes of a class are dotted.
PRIVATE_NAMES = (
    ("lerobot.envs.configs", "_make_vec_env_cls"),
    ("lerobot.envs.utils", "_LazyAsyncVectorEnv"),
    (LIBERO_MODULE, "_get_suite"),
    (LIBERO_MODULE, "_select_task_ids"),
    ("lerobot.async_inference.policy_server", f"PolicyServer.{POLICY_SERVER_CHUNK_METHOD}"),
    (DATASET_READER_MODULE, f"DatasetReader.{DATASET_READER_QUERY_METHOD}"),
    (TRAIN_MODULE, TRAIN_DATASETS_FACTORY),
)


def moved_message(module: str, name: str) -> str:
    """The error for a private name LeRobot no longer has, naming the installed and the checked version."""
    return (
        f"LeRobot {importlib.metadata.version('lerobot')} has no `{module}.{name}`, which "
        f"lerobot_policy_ebvla uses (checked against LeRobot {LEROBOT_VERSION_CHECKED}): "
        "update lerobot_private.py."
    )


def lerobot_private_name(module: str, name: str) -> Any:
    """`module.name` (a dotted `name` reaches into a class); an ImportError naming the version if it is gone."""
    try:
        target = importlib.import_module(module)
        for part in name.split("."):
            target = getattr(target, part)
    except (AttributeError, ModuleNotFoundError) as error:
        raise ImportError(moved_message(module, name)) from error
    return target


def make_vec_env_cls(use_async: bool, n_envs: int) -> type:
    """LeRobot's `_make_vec_env_cls`: gym's async vector env class for several async envs, else the sync one."""
    return lerobot_private_name("lerobot.envs.configs", "_make_vec_env_cls")(use_async, n_envs)


def lazy_async_vector_env(env_fns: list[Callable[[], Any]]) -> Any:
    """LeRobot's `_LazyAsyncVectorEnv(env_fns)`: an async vector env whose workers start at its first use."""
    return lerobot_private_name("lerobot.envs.utils", "_LazyAsyncVectorEnv")(env_fns)


def get_libero_suite(name: str) -> Any:
    """LeRobot's `_get_suite`: the LIBERO benchmark suite `name`, with a clear error for an unknown name."""
    return lerobot_private_name(LIBERO_MODULE, "_get_suite")(name)


def select_libero_task_ids(total_tasks: int, task_ids: Iterable[int] | None) -> list[int]:
    """LeRobot's `_select_task_ids`: the sorted task ids to build (all when `task_ids` is None), validated."""
    return lerobot_private_name(LIBERO_MODULE, "_select_task_ids")(total_tasks, task_ids)


def lerobot_reads_single_columns() -> bool:
    """Whether the installed LeRobot's `DatasetReader` reads delta-queried keys from their column alone."""
    reader_class = lerobot_private_name(DATASET_READER_MODULE, "DatasetReader")
    return hasattr(reader_class, DATASET_READER_COLUMN_VIEW)

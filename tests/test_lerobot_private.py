"""The private LeRobot names the plugin uses (`lerobot_private.py`) still exist in the installed LeRobot.

LeRobot may move its private names in any release; these tests fail first, naming the installed version and
the one `lerobot_private.py` was checked against. The LIBERO ones need the optional `libero` package: they run
in a subprocess with a LIBERO config of their own (importing `libero` without one asks questions on stdin),
and are skipped when `libero` is not installed.
"""

import ast
import importlib.metadata
import importlib.util
import inspect
import os
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import pytest
import yaml

from lerobot_policy_ebvla import lerobot_private
from lerobot_policy_ebvla.envs.libero_assets import default_config, libero_benchmark_root

INSTALLED = importlib.metadata.version("lerobot")
CHECKED = lerobot_private.LEROBOT_VERSION_CHECKED
NAMES = [
    (module, name)
    for module, name in lerobot_private.PRIVATE_NAMES
    if module != lerobot_private.LIBERO_MODULE
]


@pytest.mark.parametrize(("module", "name"), NAMES, ids=[f"{m}.{n}" for m, n in NAMES])
def test_every_private_lerobot_name_still_exists(module, name):
    try:
        target = lerobot_private.lerobot_private_name(module, name)
    except ImportError as error:
        pytest.fail(str(error))
    assert callable(target), lerobot_private.moved_message(module, name)


def test_vector_envs_are_chosen_as_in_the_checked_lerobot():
    message = f"LeRobot {INSTALLED}'s `_make_vec_env_cls` no longer behaves as in LeRobot {CHECKED}."
    assert lerobot_private.make_vec_env_cls(True, 2) is gym.vector.AsyncVectorEnv, message
    assert lerobot_private.make_vec_env_cls(True, 1) is gym.vector.SyncVectorEnv, message
    assert lerobot_private.make_vec_env_cls(False, 2) is gym.vector.SyncVectorEnv, message


def test_the_policy_server_method_serving_overrides_still_takes_one_observation():
    from lerobot.async_inference.policy_server import PolicyServer

    method = getattr(PolicyServer, lerobot_private.POLICY_SERVER_CHUNK_METHOD)
    assert list(inspect.signature(method).parameters) == ["self", "observation_t"], (
        f"LeRobot {INSTALLED} changed the arguments of `PolicyServer.{lerobot_private.POLICY_SERVER_CHUNK_METHOD}` "
        f"(checked against LeRobot {CHECKED}), which serving.EBVLAPolicyServer overrides."
    )


LIBERO_CHECK = """
from lerobot_policy_ebvla import lerobot_private as p

for module, name in p.PRIVATE_NAMES:
    if module == p.LIBERO_MODULE:
        p.lerobot_private_name(module, name)
assert p.select_libero_task_ids(3, None) == [0, 1, 2]
assert p.select_libero_task_ids(10, [4, 1, 4]) == [1, 4]
assert len(p.get_libero_suite("libero_object").tasks) == 10
print("OK")
"""


def test_the_libero_names_still_exist_and_the_wrappers_call_them(tmp_path):
    if importlib.util.find_spec("libero") is None:
        pytest.skip("the optional `libero` package is not installed")
    # A LIBERO config of its own: `libero` imports without asking questions, and no user file is touched.
    root = libero_benchmark_root()
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(default_config(root, root / "assets")))
    result = subprocess.run(
        [sys.executable, "-c", LIBERO_CHECK],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "LIBERO_CONFIG_PATH": str(tmp_path)},
        stdin=subprocess.DEVNULL,
    )
    assert result.returncode == 0 and "OK" in result.stdout, (
        f"LeRobot {INSTALLED}'s LIBERO helpers do not work as in LeRobot {CHECKED} (lerobot_private.py):\n"
        + result.stdout[-2000:]
        + result.stderr[-3000:]
    )


def test_no_other_module_imports_a_private_lerobot_name():
    package_dir = Path(lerobot_private.__file__).parent
    wrong = []
    for path in package_dir.rglob("*.py"):
        if path.name == "lerobot_private.py":
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "lerobot":
                wrong += [
                    f"{path.name}: {node.module}.{a.name}" for a in node.names if a.name.startswith("_")
                ]
    assert not wrong, "import these through lerobot_private.py: " + ", ".join(wrong)

"""`--policy.type=ebvla` registers whatever happens to the env types.

LeRobot's plugin loader (`register_third_party_plugins`) only logs a plugin that fails to import, so a LeRobot
release that renames a name the envs use must cost the envs alone. Each check runs in a fresh interpreter in which
LeRobot has lost the names, then loads the plugin as `lerobot-train` and `lerobot-eval` do.
"""

import importlib.metadata
import subprocess
import sys
import textwrap

import pytest

from lerobot_policy_ebvla import lerobot_private

INSTALLED = importlib.metadata.version("lerobot")

LOAD_PLUGIN = """
from lerobot.configs import PreTrainedConfig
from lerobot.envs.configs import EnvConfig
from lerobot.utils.import_utils import register_third_party_plugins

register_third_party_plugins()
from lerobot_policy_ebvla import EBVLAConfig

assert PreTrainedConfig.get_choice_class("ebvla") is EBVLAConfig
print("policy registered")
"""


def run_without(names: list[tuple[str, str]], then: str) -> subprocess.CompletedProcess:
    """Python code `then`, run after LeRobot has lost `names` ((module, attribute)) and the plugin was loaded."""
    removals = "".join(f"import {module}\ndel {module}.{attribute}\n" for module, attribute in names)
    code = removals + LOAD_PLUGIN + textwrap.dedent(then)
    return subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=300, stdin=subprocess.DEVNULL
    )


def output(result: subprocess.CompletedProcess) -> str:
    return result.stdout[-3000:] + result.stderr[-3000:]


@pytest.fixture(scope="module")
def without_private_vector_env_names() -> subprocess.CompletedProcess:
    return run_without(
        [("lerobot.envs.configs", "_make_vec_env_cls"), ("lerobot.envs.utils", "_LazyAsyncVectorEnv")],
        """
        from lerobot_policy_ebvla import lerobot_private

        assert EnvConfig.get_choice_class("metaworld_ebvla") is not None
        assert EnvConfig.get_choice_class("libero_ebvla") is not None
        print("envs registered")
        env = EnvConfig.get_choice_class("metaworld_ebvla")(task="reach-v3")
        for build in (lambda: env.create_envs(n_envs=1), lambda: lerobot_private.lazy_async_vector_env([])):
            try:
                build()
            except ImportError as error:
                print("ImportError:", error)
        """,
    )


def test_ebvla_stays_a_policy_type_when_lerobot_loses_a_private_name_the_envs_use(
    without_private_vector_env_names,
):
    result = without_private_vector_env_names
    assert result.returncode == 0 and "policy registered" in result.stdout, output(result)
    assert "envs registered" in result.stdout, output(result)


@pytest.mark.parametrize(
    "name", ["lerobot.envs.configs._make_vec_env_cls", "lerobot.envs.utils._LazyAsyncVectorEnv"]
)
def test_building_an_env_without_the_private_name_names_it_and_the_lerobot_version(
    without_private_vector_env_names, name
):
    errors = [
        line
        for line in without_private_vector_env_names.stdout.splitlines()
        if line.startswith("ImportError")
    ]
    expected = (
        f"ImportError: LeRobot {INSTALLED} has no `{name}`, which lerobot_policy_ebvla uses (checked against "
        f"LeRobot {lerobot_private.LEROBOT_VERSION_CHECKED})"
    )
    assert any(line.startswith(expected) for line in errors), output(without_private_vector_env_names)


def test_ebvla_stays_a_policy_type_when_the_env_configs_cannot_be_imported():
    result = run_without(
        [("lerobot.envs.configs", "MetaworldEnv")],
        """
        assert "metaworld_ebvla" not in EnvConfig.get_known_choices()
        print("envs not registered")
        """,
    )
    assert result.returncode == 0 and "policy registered" in result.stdout, output(result)
    assert "envs not registered" in result.stdout, output(result)
    assert f"the env types metaworld_ebvla and libero_ebvla are not registered, as LeRobot {INSTALLED}" in (
        result.stderr
    ), output(result)

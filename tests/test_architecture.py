"""The package's boundaries (docs/architecture.md): imports run one way, CLIs stay thin.

Every import counts, at module level or inside a function: a lazy import is still an arrow. Imports under
`if TYPE_CHECKING:` are annotations only: they do not count between the parts, but they do in a cycle (a module
pair that needs each other's names even for annotations is one idea split in two).
"""

import ast
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE_DIR = ROOT / "src" / "lerobot_policy_ebvla"
PACKAGE = "lerobot_policy_ebvla"

CORE = {
    "configuration_ebvla",
    "presets",
    "energy_head",
    "mcmc",
    "backbone_resnet",
    "backbone_vlm",
    "processor_ebvla",
    "modeling_ebvla",
    "compile_ebvla",
    "rtc_ebvla",
    "inputs_ebvla",
    "training_signal",
    "phase_energy",
    "configuration_groups",
}
# What each part may import from the package (besides itself). The package's own __init__ is the facade.
ALLOWED = {
    "runtime": set(),
    "core": {"runtime"},
    "envs": {"lerobot_private"},
    "lerobot_private": set(),
    "recording": {"envs", "lerobot_private"},
    "monitoring": {"core", "runtime"},
    "pipelines": {"core", "runtime", "envs", "lerobot_private", "recording", "monitoring"},
    "scripts": {
        "core",
        "runtime",
        "envs",
        "lerobot_private",
        "recording",
        "monitoring",
        "pipelines",
        "serving",
        "facade",
    },
    "serving": {"core", "runtime", "lerobot_private"},
    "facade": {"core", "runtime", "envs"},
}
CLI_MAX_LINES = 150


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE_DIR.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def part_of(module: str) -> str:
    """The part (see ALLOWED) a package module belongs to."""
    parts = module.split(".")
    if len(parts) == 1:
        return "facade"
    if parts[1] in CORE:
        return "core"
    return parts[1]


def _type_checking_nodes(tree: ast.AST) -> set[int]:
    skipped = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skipped |= {id(child) for stmt in node.body for child in ast.walk(stmt)}
    return skipped


def imported_modules(path: Path, module: str, type_checking: bool = False) -> set[str]:
    """The package modules `path` imports, absolute or relative, anywhere in the file (under `if TYPE_CHECKING:`
    only with `type_checking`)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    skipped = set() if type_checking else _type_checking_nodes(tree)
    is_package = path.name == "__init__.py"
    found = set()
    for node in ast.walk(tree):
        if id(node) in skipped:
            continue
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names if alias.name.split(".")[0] == PACKAGE}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")[: len(module.split(".")) - node.level + (1 if is_package else 0)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != PACKAGE:
                continue
            # `from . import envs` or `from .monitoring import plots` imports a module by name.
            submodules = {f"{target}.{alias.name}" for alias in node.names}
            found |= {name for name in submodules if name in MODULES} or {target}
    return {name for name in found if name != module}


MODULES = {module_name(path): path for path in PACKAGE_DIR.rglob("*.py")}
GRAPH = {module: imported_modules(path, module) for module, path in MODULES.items()}
GRAPH_WITH_TYPE_CHECKING = {
    module: imported_modules(path, module, type_checking=True) for module, path in MODULES.items()
}


def _resolve(name: str) -> str:
    """An imported name as a module of the package (a function imported from a module names the module)."""
    while name not in MODULES and "." in name:
        name = name.rsplit(".", 1)[0]
    return name


def find_cycle() -> list[str] | None:
    graph = {module: {_resolve(n) for n in targets} for module, targets in GRAPH_WITH_TYPE_CHECKING.items()}
    # A package's __init__ re-exporting its own modules is not a cycle with them.
    graph = {m: {t for t in ts if not m.startswith(f"{t}.")} for m, ts in graph.items()}
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for target in sorted(graph.get(node, ())):
            if state.get(target) == 1:
                return stack[stack.index(target) :] + [target]
            if target not in state and (cycle := visit(target)):
                return cycle
        stack.pop()
        state[node] = 2
        return None

    for module in sorted(graph):
        if module not in state and (cycle := visit(module)):
            return cycle
    return None


def test_the_package_has_no_import_cycle_even_through_type_only_imports():
    cycle = find_cycle()
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_imports_run_one_way_between_the_parts():
    wrong = []
    for module, targets in GRAPH.items():
        part = part_of(module)
        for target in targets:
            other = part_of(_resolve(target))
            if other != part and other not in ALLOWED[part]:
                wrong.append(f"{module} ({part}) imports {target} ({other})")
    assert not wrong, "\n".join(sorted(wrong))


def test_the_policy_core_imports_nothing_from_the_analysis():
    core = [m for m in GRAPH if part_of(m) in ("core", "runtime")]
    assert core, "the layout changed: no core module found"
    for module in core:
        assert not {
            t for t in GRAPH[module] if part_of(_resolve(t)) in ("monitoring", "pipelines", "scripts")
        }


def test_no_library_module_benchmark_or_example_imports_a_cli():
    users = [(m, p) for m, p in MODULES.items() if part_of(m) != "scripts"]
    users += [
        (p.stem, p) for folder in ("research/benchmarks", "examples") for p in (ROOT / folder).rglob("*.py")
    ]
    wrong = []
    for name, path in users:
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            target = getattr(node, "module", None) or ""
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else []
            if f"{PACKAGE}.scripts" in target or any(n.startswith(f"{PACKAGE}.scripts") for n in names):
                wrong.append(f"{name} imports {target or names}")
    assert not wrong, "\n".join(wrong)


@pytest.mark.parametrize("path", sorted((PACKAGE_DIR / "scripts").glob("*.py")), ids=lambda p: p.name)
def test_every_cli_is_a_thin_main(path):
    lines = len(path.read_text(encoding="utf-8").splitlines())
    assert lines <= CLI_MAX_LINES, f"{path.name} has {lines} lines: move its logic into the library"


def test_importing_the_policy_and_building_one_loads_no_analysis_and_no_matplotlib():
    code = textwrap.dedent(
        """
        import sys
        from lerobot.configs.types import FeatureType, PolicyFeature
        from lerobot_policy_ebvla import EBVLAPolicy
        from lerobot_policy_ebvla.presets import light_policy_config

        config = light_policy_config(
            input_features={
                "observation.image": PolicyFeature(FeatureType.VISUAL, (3, 64, 64)),
                "observation.state": PolicyFeature(FeatureType.STATE, (4,)),
            },
            output_features={"action": PolicyFeature(FeatureType.ACTION, (4,))},
            resnet={"task_instructions": ["press the button"]},
        )
        EBVLAPolicy(config)
        loaded = sorted(m for m in sys.modules if m.split(".")[0] == "matplotlib" or any(
            m.startswith(f"lerobot_policy_ebvla.{part}") for part in ("monitoring", "pipelines", "scripts")
        ))
        print("LOADED", loaded)
        """
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "LOADED []" in result.stdout, result.stdout[-2000:]

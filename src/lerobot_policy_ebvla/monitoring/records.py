"""Energy records: one row per predicted action chunk, the data every monitoring tool reads.

`ebvla-eval` writes them as JSON lines to `energy_records.jsonl`, next to lerobot-eval's `eval_info.json`:

    {"episode_index": 0, "chunk_index": 0, "env_step": 0, "initial_energy": 7.31, "final_energy": 5.92,
     "success": true, "task": "pick up the cup", "seed": 1000, "perturbation": "none", "severity": 0.0}

JSON has no infinity, and the policy reports `+inf` when refinement went non-finite, so non-finite energies
are written as the strings "inf", "-inf" and "nan". Reading accepts those strings, plain numbers and the
`Infinity`/`NaN` tokens Python's `json` module emits, so a file round-trips exactly.

Opt-in fields of the recorder (`monitoring/recorder.py`) add to a row (older files and rows without them
read as None):
- `restart_spread` and `normalized_energy`: written in the row when recorded;
- `held`: written when the policy has an OOD response: whether it replaced the chunk by its hold action;
- `context_feature`: a (D,) vector per row, stored compactly beside the records as float32 rows of
  `energy_records.features.npy` (row i belongs to line i of the records), attached to the records on read.

Records to commit are gzip-compressed: `energy_records.jsonl.gz`, its features
`energy_records.features.npy.gz` (the same bytes, gzipped). Both are written without a timestamp, so
compressing the same records twice gives the same bytes. Every reader takes either form (a folder must hold
one of them, not both); `compress_records` turns a folder of records into the compressed form:

    python -m lerobot_policy_ebvla.monitoring.records --paths='[research/results/my_study]'
"""

import dataclasses
import glob
import gzip
import io
import json
import math
import os
import sys
import tempfile
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

ENERGY_RECORDS_FILENAME = "energy_records.jsonl"
GZIP_SUFFIX = ".gz"
COMPRESSED_RECORDS_FILENAME = ENERGY_RECORDS_FILENAME + GZIP_SUFFIX
VANILLA_PERTURBATION = "none"
FEATURES_SUFFIX = ".features.npy"
# Fields every row has had since the first version of the format; later fields are optional on read.
_REQUIRED_FIELDS = (
    "episode_index",
    "chunk_index",
    "env_step",
    "initial_energy",
    "final_energy",
    "success",
    "task",
    "seed",
    "perturbation",
    "severity",
)

_NON_FINITE_TO_STR = {math.inf: "inf", -math.inf: "-inf"}
_STR_TO_NON_FINITE = {"inf": math.inf, "+inf": math.inf, "-inf": -math.inf, "nan": math.nan}


@dataclass(frozen=True)
class EnergyRecord:
    """Energies of one predicted action chunk, and the episode it belongs to.

    Args:
        episode_index: Index of the evaluation episode (as in lerobot-eval, per task).
        chunk_index: 0-based index of the chunk within its episode.
        env_step: Environment step at which the chunk was predicted.
        initial_energy: E(a^(0), C), the energy of the unrefined initial sample.
        final_energy: E(a^(K_inf), C), the energy after MCMC refinement (the paper's confidence score).
        success: Whether the episode succeeded (repeated on each of its rows).
        task: Task instruction or name of the episode.
        seed: Environment seed of the episode, None when unseeded.
        perturbation: Name of the applied perturbation, "none" for vanilla (in-distribution) rollouts.
        severity: Perturbation severity, 0 for vanilla rollouts.
        restart_spread: Baseline: the spread (std over chains, mean over the chunk) of N refined chunks for
            the same observation; None when not recorded.
        normalized_energy: Score: the final energy relative to the context's own energy scale,
            E(a^(K_inf), C) + log mean_j exp(-E(a_j, C)) over N chunks a_j drawn from the MCMC prior; None
            when not recorded.
        mcmc_chains: How many MCMC chains were refined for this chunk (`num_restarts`; with adaptive
            restarts 1, or `num_restarts` where the first chain's energy was above the threshold): the
            chunk's compute; None when not recorded.
        held: Whether the policy's OOD response (`EBVLAConfig.monitor.response="hold"`) replaced this chunk by
            the hold action; None when the policy has no OOD response.
        context_energy: E_c(C), the joint energy's context term, already inside `final_energy` (its head's
            part is the difference); None for a policy without one.
        context_feature: Baseline: the (D,) pooled backbone context of the observation; None when not
            recorded. Stored in the `.features.npy` file beside the records, not in the JSON row.
        goal_distance: How far the task's object was from its goal, in metres, in the observation the chunk
            was predicted from (the env's `info["goal_distance"]`: LIBERO's `In` goals); None where the env
            reports none. It dates a failure's onset: the last chunk at which the object still came closer.
        phase_energy: E_tau(C, t), the phase energy of the chunk's context at its index (`phase_energy.py`); None
            for a policy without a fitted one.
    """

    episode_index: int
    chunk_index: int
    env_step: int
    initial_energy: float
    final_energy: float
    success: bool
    task: str
    seed: int | None
    perturbation: str = VANILLA_PERTURBATION
    severity: float = 0.0
    restart_spread: float | None = None
    normalized_energy: float | None = None
    held: bool | None = None
    mcmc_chains: int | None = None
    context_energy: float | None = None
    context_feature: np.ndarray | None = field(default=None, compare=False, repr=False)
    goal_distance: float | None = None
    phase_energy: float | None = None

    @property
    def is_vanilla(self) -> bool:
        return self.perturbation == VANILLA_PERTURBATION


# One rollout's chunk records, in chunk order.
Episode = Sequence[EnergyRecord]


class EpisodeKey(NamedTuple):
    """Identifies an episode in a record file: lerobot-eval restarts `episode_index` for each task."""

    perturbation: str
    severity: float
    task: str
    episode_index: int


def episode_key(record: EnergyRecord) -> EpisodeKey:
    return EpisodeKey(record.perturbation, record.severity, record.task, record.episode_index)


def _energy_to_json(value: float) -> float | str:
    if math.isnan(value):
        return "nan"
    return _NON_FINITE_TO_STR.get(value, value)


def record_to_json(record: EnergyRecord) -> str:
    """Serializes one record to a JSON line (without the newline), non-finite energies as strings."""
    row = {name: getattr(record, name) for name in _REQUIRED_FIELDS}
    row["initial_energy"] = _energy_to_json(record.initial_energy)
    row["final_energy"] = _energy_to_json(record.final_energy)
    if record.restart_spread is not None:
        row["restart_spread"] = _energy_to_json(record.restart_spread)
    if record.normalized_energy is not None:
        row["normalized_energy"] = _energy_to_json(record.normalized_energy)
    if record.held is not None:
        row["held"] = record.held
    if record.mcmc_chains is not None:
        row["mcmc_chains"] = record.mcmc_chains
    if record.context_energy is not None:
        row["context_energy"] = _energy_to_json(record.context_energy)
    if record.goal_distance is not None:
        row["goal_distance"] = _energy_to_json(record.goal_distance)
    if record.phase_energy is not None:
        row["phase_energy"] = _energy_to_json(record.phase_energy)
    return json.dumps(row, allow_nan=False)


def is_compressed(path: str | Path) -> bool:
    return Path(path).name.endswith(GZIP_SUFFIX)


def features_path(records_path: str | Path) -> Path:
    """Where a records file's context features are written: `energy_records.features.npy` beside it, or
    `energy_records.features.npy.gz` beside a compressed `energy_records.jsonl.gz`."""
    records_path = Path(records_path)
    name = records_path.name.removesuffix(GZIP_SUFFIX)
    features = Path(name).stem + FEATURES_SUFFIX
    return records_path.with_name(features + (GZIP_SUFFIX if is_compressed(records_path) else ""))


def _features_paths(records_path: Path) -> list[Path]:
    """Where a records file's features may be, its own form first: records compressed by hand keep theirs."""
    written = features_path(records_path)
    other = written.with_name(written.name.removesuffix(GZIP_SUFFIX)) if is_compressed(written) else None
    return [written, other or written.with_name(written.name + GZIP_SUFFIX)]


def _save_features(features: np.ndarray, compressed: bool) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, features)
    return gzip.compress(buffer.getvalue(), mtime=0) if compressed else buffer.getvalue()


def _load_features(path: Path) -> np.ndarray:
    data = path.read_bytes()
    return np.load(io.BytesIO(gzip.decompress(data) if is_compressed(path) else data))


def _stack_features(records: list[EnergyRecord]) -> np.ndarray | None:
    with_feature = [r.context_feature is not None for r in records]
    if not any(with_feature):
        return None
    if not all(with_feature):
        raise ValueError(
            f"{with_feature.count(False)} of {len(records)} records have no `context_feature`: record "
            "features for every chunk or for none."
        )
    return np.stack([np.asarray(r.context_feature, dtype=np.float32) for r in records])


def _write_atomically(path: Path, write) -> None:
    fd, tmp_name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
        os.replace(tmp_name, path)
    except BaseException:
        Path(tmp_name).unlink(missing_ok=True)
        raise


def write_energy_records(path: str | Path, records: Iterable[EnergyRecord], overwrite: bool = False) -> Path:
    """Writes records as JSON lines, atomically: to a temporary file in the same folder, then renamed.

    The rename means a reader never sees a half-written file, even if evaluation is killed mid-write.

    Args:
        path: Destination file, usually `<eval output dir>/energy_records.jsonl`; a name ending in `.gz`
            writes gzip-compressed records (and features).
        records: The records, written in the given order.
        overwrite: Replace an existing file. Without it an existing file is an error.

    Returns:
        The path written.

    Raises:
        FileExistsError: `path` exists and `overwrite` is False.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} already exists; pass overwrite=True to replace it.")
    path.parent.mkdir(parents=True, exist_ok=True)
    records = list(records)
    features = _stack_features(records)
    compressed = is_compressed(path)
    text = "".join(record_to_json(record) + "\n" for record in records).encode("utf-8")
    if compressed:
        text = gzip.compress(text, mtime=0)
    # Features first: a reader that finds the new records also finds their features.
    written = features_path(path)
    if features is None:
        written.unlink(missing_ok=True)  # a previous run's features no longer match
    else:
        data = _save_features(features, compressed)
        _write_atomically(written, lambda f: f.write(data))
    _write_atomically(path, lambda f: f.write(text))
    return path


def _parse_int(value: Any, name: str, where: str) -> int:
    # bool is an int subclass in Python; a boolean where an index belongs is a bug in the writer.
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"{where}: field `{name}` must be an integer, got {value!r}.")
    return value


def _parse_float(value: Any, name: str, where: str) -> float:
    if isinstance(value, str) and value.strip().lower() in _STR_TO_NON_FINITE:
        return _STR_TO_NON_FINITE[value.strip().lower()]
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(
            f'{where}: field `{name}` must be a number or one of "inf", "-inf", "nan", got {value!r}.'
        )
    return float(value)


def record_from_json(row: dict[str, Any], where: str = "record") -> EnergyRecord:
    """Builds a record from a decoded JSON object, validating every field.

    Args:
        row: The decoded object.
        where: Location used in error messages, e.g. "energy_records.jsonl:12".

    Raises:
        ValueError: A field is missing or has the wrong type; the message names it and `where`.
    """
    if not isinstance(row, dict):
        raise ValueError(f"{where}: expected a JSON object, got {type(row).__name__}.")
    missing = [name for name in _REQUIRED_FIELDS if name not in row]
    if missing:
        raise ValueError(f"{where}: missing field(s) {', '.join(f'`{m}`' for m in missing)}.")
    if not isinstance(row["success"], bool):
        raise ValueError(f"{where}: field `success` must be true or false, got {row['success']!r}.")
    for name in ("task", "perturbation"):
        if not isinstance(row[name], str):
            raise ValueError(f"{where}: field `{name}` must be a string, got {row[name]!r}.")
    seed = row["seed"]
    return EnergyRecord(
        episode_index=_parse_int(row["episode_index"], "episode_index", where),
        chunk_index=_parse_int(row["chunk_index"], "chunk_index", where),
        env_step=_parse_int(row["env_step"], "env_step", where),
        initial_energy=_parse_float(row["initial_energy"], "initial_energy", where),
        final_energy=_parse_float(row["final_energy"], "final_energy", where),
        success=row["success"],
        task=row["task"],
        seed=None if seed is None else _parse_int(seed, "seed", where),
        perturbation=row["perturbation"],
        severity=_parse_float(row["severity"], "severity", where),
        restart_spread=_parse_optional_float(row, "restart_spread", where),
        normalized_energy=_parse_optional_float(row, "normalized_energy", where),
        held=_parse_optional_bool(row.get("held"), "held", where),
        mcmc_chains=None
        if row.get("mcmc_chains") is None
        else _parse_int(row["mcmc_chains"], "mcmc_chains", where),
        context_energy=_parse_optional_float(row, "context_energy", where),
        goal_distance=_parse_optional_float(row, "goal_distance", where),
        phase_energy=_parse_optional_float(row, "phase_energy", where),
    )


def _parse_optional_float(row: dict[str, Any], name: str, where: str) -> float | None:
    """An optional number field: None when absent (or null), as files written before the field was had it."""
    return None if row.get(name) is None else _parse_float(row[name], name, where)


def _parse_optional_bool(value: Any, name: str, where: str) -> bool | None:
    if value is not None and not isinstance(value, bool):
        raise ValueError(f"{where}: field `{name}` must be true, false or absent, got {value!r}.")
    return value


def records_file_in(folder: str | Path) -> Path | None:
    """The records file of a folder: its `energy_records.jsonl` or `energy_records.jsonl.gz`, None if neither.

    Raises:
        ValueError: The folder holds both (which one is meant?).
    """
    folder = Path(folder)
    found = [f for f in (ENERGY_RECORDS_FILENAME, COMPRESSED_RECORDS_FILENAME) if (folder / f).is_file()]
    if len(found) > 1:
        raise ValueError(f"{folder} holds both {' and '.join(found)}: remove the one that is not meant.")
    return folder / found[0] if found else None


def read_energy_records(path: str | Path) -> list[EnergyRecord]:
    """Reads an `energy_records.jsonl` file, or a compressed `energy_records.jsonl.gz`. Skips blank lines.

    Args:
        path: The file, or a folder holding one of them.

    Raises:
        FileNotFoundError: The file does not exist.
        ValueError: A line is not valid JSON or a field is missing or malformed; the message gives the
            file, the 1-based line number and the field.
    """
    path = Path(path)
    if path.is_dir():
        path = records_file_in(path) or path / ENERGY_RECORDS_FILENAME
    records = []
    with (
        gzip.open(path, "rt", encoding="utf-8") if is_compressed(path) else open(path, encoding="utf-8") as f
    ):
        for line_number, line in enumerate(f, start=1):
            if not line.strip():
                continue
            where = f"{path}:{line_number}"
            try:
                row = json.loads(line)
            except json.JSONDecodeError as e:
                raise ValueError(f"{where}: invalid JSON ({e.msg}).") from e
            records.append(record_from_json(row, where))
    found = [f for f in _features_paths(path) if f.exists()]
    if found:
        features = _load_features(found[0])
        if features.ndim != 2 or features.shape[0] != len(records):
            raise ValueError(
                f"{found[0]}: expected ({len(records)}, D) context features, one row per record "
                f"of {path}, got shape {features.shape}."
            )
        records = [dataclasses.replace(r, context_feature=f) for r, f in zip(records, features, strict=True)]
    return records


def group_by_episode(records: Iterable[EnergyRecord]) -> dict[EpisodeKey, list[EnergyRecord]]:
    """Groups records by episode, each episode's chunks sorted by `chunk_index`.

    Episodes are keyed by (perturbation, severity, task, episode_index) because lerobot-eval numbers
    episodes per task. Episodes keep the order in which they first appear.

    Raises:
        ValueError: An episode has two rows with the same `chunk_index` (e.g. two runs' files were
            concatenated) or rows that disagree on `success`.
    """
    episodes: dict[EpisodeKey, list[EnergyRecord]] = {}
    for record in records:
        episodes.setdefault(episode_key(record), []).append(record)
    for key, chunks in episodes.items():
        chunks.sort(key=lambda r: r.chunk_index)
        indices = [r.chunk_index for r in chunks]
        if len(set(indices)) != len(indices):
            raise ValueError(f"Episode {key} has duplicate chunk indices; were two record files merged?")
        if len({r.success for r in chunks}) > 1:
            raise ValueError(f"Episode {key} has rows that disagree on `success`.")
    return episodes


def resolve_record_files(paths: Iterable[str | Path]) -> list[Path]:
    """The record files named by paths: files, eval folders (their `energy_records.jsonl` or
    `energy_records.jsonl.gz`) or glob patterns.

    Raises:
        FileNotFoundError: A path or pattern names no record file.
        ValueError: A folder holds both forms.
    """
    files = []
    for pattern in paths:
        pattern = str(pattern)
        matches = (
            [Path(m) for m in sorted(glob.glob(pattern))] if glob.has_magic(pattern) else [Path(pattern)]
        )
        found = [records_file_in(m) if m.is_dir() else m for m in matches]
        found = [f.resolve() for f in found if f and f.is_file()]  # one spelling per file: overlaps are found
        if not found:
            raise FileNotFoundError(
                f"No {ENERGY_RECORDS_FILENAME} (or {COMPRESSED_RECORDS_FILENAME}) found at {pattern}."
            )
        files += found
    return list(dict.fromkeys(files))


def load_episodes(
    paths: Iterable[str | Path], perturbations: Iterable[str] | None = None
) -> dict[tuple[str, EpisodeKey], list[EnergyRecord]]:
    """The episodes of record files, keyed by (file, episode): episode indices restart in every run.

    Args:
        paths: See `resolve_record_files`.
        perturbations: Keep only rows with these perturbation names (e.g. ["none"]); None keeps all.
    """
    keep = None if perturbations is None else set(perturbations)
    episodes = {}
    for path in resolve_record_files(paths):
        records = read_energy_records(path)
        if keep is not None:
            records = [r for r in records if r.perturbation in keep]
        for key, chunks in group_by_episode(records).items():
            episodes[(str(path), key)] = chunks
    return episodes


def compress_records(paths: Iterable[str | Path], keep_original: bool = False) -> list[Path]:
    """Compresses records for committing: each `energy_records.jsonl` into `energy_records.jsonl.gz`.

    Each file (or every `energy_records.jsonl` below each folder) is read, written compressed beside itself
    with its features, read back and compared, and only then, unless `keep_original`, removed with its
    features (a folder holding both forms would be refused by every reader).

    Returns:
        The compressed files written.

    Raises:
        FileNotFoundError: A path names no records file.
    """
    files = []
    for path in map(Path, paths):
        found = sorted(path.rglob(ENERGY_RECORDS_FILENAME)) if path.is_dir() else [path]
        if not found or not all(f.is_file() for f in found):
            raise FileNotFoundError(f"No {ENERGY_RECORDS_FILENAME} found at {path}.")
        files += found
    written = []
    for file in files:
        records = read_energy_records(file)
        target = write_energy_records(file.with_name(file.name + GZIP_SUFFIX), records, overwrite=True)
        _check_same_records(records, read_energy_records(target), target)
        if not keep_original:
            features_path(file).unlink(missing_ok=True)
            file.unlink()
        written.append(target)
    return written


def _check_same_records(expected: list[EnergyRecord], read: list[EnergyRecord], path: Path) -> None:
    # Compared as their JSON lines: a NaN energy equals itself there, not as a float.
    same = [record_to_json(r) for r in read] == [record_to_json(r) for r in expected]
    features = _stack_features(read), _stack_features(expected)
    if any(f is not None for f in features):
        same = same and all(f is not None for f in features) and np.array_equal(*features, equal_nan=True)
    if not same:
        raise RuntimeError(f"{path} does not read back as the records it was written from; originals kept.")


@dataclass
class CompressRecordsConfig:
    """Compresses energy records for committing (`compress_records`)."""

    # Records files, or folders searched recursively for `energy_records.jsonl`.
    paths: list[str] = field(default_factory=list)
    # Keep the uncompressed files (readers then refuse the folder until one form is removed).
    keep_original: bool = False


def main(args: list[str] | None = None) -> None:
    import draccus  # only this command parses a config: the records need no draccus

    cfg = draccus.parse(CompressRecordsConfig, args=sys.argv[1:] if args is None else args)
    for path in compress_records(cfg.paths, cfg.keep_original):
        sys.stdout.write(f"{path}\n")


if __name__ == "__main__":
    main()

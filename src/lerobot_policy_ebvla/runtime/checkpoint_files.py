"""Files saved beside a checkpoint's weights: one JSON file per calibration, and the safetensors files it names.

`CheckpointJSON` is the one way a calibration (`OODCalibration`, `FailureAlarm`) is saved into a policy's
`pretrained_model` folder and read back from it, locally or from a Hugging Face Hub model repository.

Numbers too many for JSON (a D x D precision, every calibration context) go into a safetensors file beside it
(`SideFile`); the JSON names the file with a description of what it holds and its SHA-256, so that a file of
another calibration is refused on loading.
"""

import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Self


class CheckpointJSON:
    """A calibration saved as one JSON file in a policy checkpoint folder (the `pretrained_model` folder).

    A subclass names its file and says how it becomes a JSON object (`to_json`) and back (`from_json`); this
    class checks the folder, never overwrites unless asked, and finds the file locally or on the Hub.
    """

    filename: ClassVar[str]
    # What the file holds and the command that writes it, for error messages.
    what: ClassVar[str]
    command: ClassVar[str]

    def to_json(self, checkpoint_dir: Path) -> dict[str, Any]:
        """The JSON object to write; side files are written into `checkpoint_dir` here, before the JSON."""
        raise NotImplementedError

    @classmethod
    def from_json(cls, payload: dict[str, Any], path: Path) -> Self:
        """Builds the calibration from the JSON object read at `path` (raises ValueError or TypeError)."""
        raise NotImplementedError

    @classmethod
    def expected_fields(cls) -> str:
        """The fields a valid file has, for the error on an invalid one."""
        raise NotImplementedError

    def save(self, checkpoint_dir: str | Path, overwrite: bool = False) -> Path:
        """Writes the JSON file into a policy checkpoint folder (the `pretrained_model` folder).

        Raises:
            FileNotFoundError: The folder does not exist.
            ValueError: The folder is a training checkpoint that holds a `pretrained_model` folder.
            FileExistsError: The file exists and `overwrite` is False.
        """
        checkpoint_dir = Path(checkpoint_dir)
        if not checkpoint_dir.is_dir():
            raise FileNotFoundError(f"Checkpoint folder {checkpoint_dir} does not exist.")
        if (checkpoint_dir / "pretrained_model").is_dir():
            raise ValueError(
                f"{checkpoint_dir} holds a `pretrained_model` folder; save the {self.what} there, next to "
                "the policy's config.json, so `from_pretrained` finds it."
            )
        path = checkpoint_dir / self.filename
        if path.exists() and not overwrite:
            raise FileExistsError(f"{path} already exists; pass overwrite=True to replace it.")
        payload = self.to_json(checkpoint_dir)
        path.write_text(json.dumps(payload, indent=2, allow_nan=False) + "\n", encoding="utf-8")
        return path

    @classmethod
    def load(cls, path: str | Path) -> Self:
        """Reads the JSON file, or the checkpoint folder that holds it."""
        path = Path(path)
        if path.is_dir():
            path = path / cls.filename
        try:
            payload = json.loads(path.read_text(encoding="utf-8"))
            if not isinstance(payload, dict):
                raise TypeError(f"expected a JSON object, got {type(payload).__name__}")
            return cls.from_json(payload, path)
        except (json.JSONDecodeError, TypeError, ValueError) as e:
            raise ValueError(
                f"{path} is not a valid {cls.what} ({e}). Expected a JSON object with the fields "
                f"{cls.expected_fields()}, as `{cls.command} --calibrate_to` writes it: calibrate again, or remove "
                "the file."
            ) from e

    @classmethod
    def from_pretrained(cls, pretrained_name_or_path: str | Path) -> Self:
        """Loads it from a local checkpoint folder or a Hugging Face Hub model repository (with the side
        files its JSON names)."""
        if Path(pretrained_name_or_path).exists():
            return cls.load(pretrained_name_or_path)
        from huggingface_hub import hf_hub_download

        repo_id = str(pretrained_name_or_path)
        try:
            path = Path(hf_hub_download(repo_id, cls.filename))
        except Exception as e:  # a mistyped local path reaches the Hub as an invalid repo id
            raise FileNotFoundError(
                f"No {cls.filename} in a local folder or Hub repo named {pretrained_name_or_path}; "
                f"create it with `{cls.command} --calibrate_to=...`."
            ) from e
        for field, name in _side_files_named(path):
            try:
                hf_hub_download(repo_id, name)  # into the same snapshot folder, beside the JSON
            except Exception as e:
                raise ValueError(
                    f"The {cls.filename} of the Hub repo {repo_id} names `{field}.file` = {name!r}, which cannot "
                    f"be downloaded ({e}): upload it beside the JSON, or calibrate again."
                ) from e
        return cls.load(path)


def _side_files_named(path: Path) -> list[tuple[str, str]]:
    """(field, file name) of each side file a JSON file names; none when it cannot be read (`load` then says
    what is wrong)."""
    try:
        payload = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        return []
    if not isinstance(payload, dict):
        return []
    return [
        (field, entry["file"])
        for field, entry in payload.items()
        if isinstance(entry, dict) and isinstance(entry.get("file"), str)
    ]


@dataclass(frozen=True)
class SideFile:
    """Statistics saved beside the JSON in a safetensors file that the JSON's `field` names.

    Args:
        field: The JSON field that names the file, with `describe`'s numbers and its SHA-256.
        filename: The file, beside the JSON.
        what: What it holds, for error messages.
        read: Builds the statistics from the file's bytes (their `from_bytes`); they write them with `to_bytes`.
        describe: The numbers the JSON records about them (their D, N, ...), checked against the file on loading.
    """

    field: str
    filename: str
    what: str
    read: Callable[[bytes], Any]
    describe: Callable[[Any], dict[str, int]]

    def write(self, checkpoint_dir: Path, statistics: Any) -> dict[str, Any]:
        """Writes the file into `checkpoint_dir` and returns the JSON entry that names it."""
        data = statistics.to_bytes()
        (checkpoint_dir / self.filename).write_bytes(data)
        return {
            "file": self.filename,
            **self.describe(statistics),
            "sha256": hashlib.sha256(data).hexdigest(),
        }

    def load(self, path: Path, entry: object) -> Any:
        """The statistics of the JSON at `path`'s entry, checked against it: the file exists beside the JSON,
        has the recorded SHA-256, and holds what the entry describes."""
        if not isinstance(entry, dict) or "file" not in entry or "sha256" not in entry:
            raise ValueError(
                f"`{self.field}` must be an object with the keys `file` and `sha256`, got {entry!r}"
            )
        name = entry["file"]
        if not isinstance(name, str) or Path(name).name != name or name in ("", ".", ".."):
            raise ValueError(f"`{self.field}.file` must be a file name beside the JSON, got {name!r}")
        beside_path = path.with_name(name)
        if not beside_path.is_file():
            raise ValueError(
                f"`{self.field}.file` names {beside_path}, which does not exist: the {self.what} are saved "
                "beside the JSON and must travel with it"
            )
        data = beside_path.read_bytes()
        if hashlib.sha256(data).hexdigest() != entry["sha256"]:
            raise ValueError(
                f"{beside_path} does not match `{self.field}.sha256`: it belongs to another calibration"
            )
        try:
            statistics = self.read(data)
        except ValueError as e:
            raise ValueError(f"{beside_path}: {e}") from e
        described = self.describe(statistics)
        keys = {"file", *described, "sha256"}
        if set(entry) != keys:
            raise ValueError(f"`{self.field}` must be an object with the keys {sorted(keys)}, got {entry!r}")
        recorded = {key: entry[key] for key in described}
        if described != recorded:
            raise ValueError(
                f"{beside_path} holds {self.what} with {described}, but `{self.field}` says {recorded}"
            )
        return statistics

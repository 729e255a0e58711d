"""Fit a trained checkpoint's phase energy E_tau(C, t) on its training demonstrations, and save the checkpoint with it.

The body of `ebvla-fit-phase-energy`: load the policy and its pre-processor, read the pooled context of every
demonstration frame at a multiple of `n_action_steps` (the frames the policy would refine a chunk from, t = the
frame's chunk index), fit `phase_energy.PhaseEnergy` on them (`fit_phase_energy`) and save a new checkpoint folder:
the policy with E_tau, its processors, and the source's OOD calibration (E and E_c are unchanged). The source's failure
calibration is left behind: the checkpoint's failure check becomes `success_energy` (E_s(C, t), fitted at
calibration on the successful rollouts' pooled contexts), which needs new calibration rollouts recorded with their
contexts (`ebvla-ood-report --calibrate_to`); `joint_phase_time_energy`, which reads E_tau, is the option
beside it. The source folder is never written to.
"""

import json
import logging
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from ..configuration_groups import PHASE_FITTED_FAILURE_SCORE, PhaseEnergyConfig
from ..phase_energy import PhaseEnergy, fit_phase_energy
from ..runtime.calibration import FAILURE_CALIBRATION_FILENAME

FIT_SUMMARY_FILENAME = "phase_energy_fit.json"
# Written by the policy's and processors' `save_pretrained`, or left behind on purpose: not copied from the source.
_NOT_COPIED = {"config.json", "model.safetensors", FAILURE_CALIBRATION_FILENAME, FIT_SUMMARY_FILENAME}


@dataclass
class FitPhaseEnergyConfig:
    """The phase energy of a trained checkpoint, fitted on the demonstrations it was trained on."""

    # Local `pretrained_model` folder or Hub repo id of the trained policy.
    policy_path: str | None = None
    # The LeRobotDataset the policy was trained on (its repo id), and its local root.
    dataset_repo_id: str | None = None
    dataset_root: Path | None = None
    # Chunk bins of p(t | C): chunk indices from `bins - 1` on share the last bin.
    bins: int = 40
    # Width of the MLP of the bins' energies.
    hidden: int = 256
    # Frames per backbone pass.
    batch_size: int = 64
    # Torch device; default: the policy config's.
    device: str | None = None
    # Seed of the fit (its held-out episodes and its weights).
    seed: int = 0
    # The new checkpoint folder: must not exist yet, or be empty.
    output_dir: Path | None = None

    def validate(self) -> None:
        # Not __post_init__: draccus would wrap the ValueError in a less readable ParsingError.
        for name in ("policy_path", "dataset_repo_id", "output_dir"):
            if getattr(self, name) is None:
                raise ValueError(f"`{name}` is required.")
        if self.bins < 2:
            raise ValueError(
                f"`bins` must be >= 2 (chunk indices that p(t | C) tells apart). Got {self.bins}."
            )
        if self.hidden < 1:
            raise ValueError(f"`hidden` must be >= 1. Got {self.hidden}.")
        if self.batch_size < 1:
            raise ValueError(f"`batch_size` must be >= 1. Got {self.batch_size}.")
        if self.output_dir.exists() and any(self.output_dir.iterdir()):
            raise ValueError(
                f"`output_dir` {self.output_dir} is not empty: the fitted checkpoint is written to a new folder, so "
                "that nothing saved there is overwritten."
            )
        if Path(self.policy_path).resolve() == self.output_dir.resolve():
            raise ValueError(
                "`output_dir` must differ from `policy_path`: the source checkpoint stays as it was."
            )


def demonstration_contexts(policy, preprocessor, dataset, batch_size: int) -> dict[str, np.ndarray]:
    """The pooled context (`EBVLAPolicy.context_features`) of every frame of `dataset` whose index in its episode is a
    multiple of the policy's `n_action_steps`, with that frame's chunk index and episode."""
    stride = policy.config.n_action_steps
    frame = np.asarray(dataset.hf_dataset["frame_index"])
    rows = np.flatnonzero(frame % stride == 0)
    keys = list(policy.config.input_features)
    features = []
    for start in range(0, len(rows), batch_size):
        items = [dataset[int(i)] for i in rows[start : start + batch_size]]
        batch = {key: torch.stack([item[key] for item in items]) for key in keys}
        batch["task"] = [item["task"] for item in items]
        with torch.no_grad():
            features.append(policy.context_features(preprocessor(batch)).float().cpu().numpy())
    return {
        "features": np.concatenate(features),
        "chunk_index": frame[rows] // stride,
        "episode": np.asarray(dataset.hf_dataset["episode_index"])[rows],
    }


def _source_folder(policy_path: str) -> Path:
    """The checkpoint's local folder: the path itself, or the Hub snapshot of a repo id."""
    if Path(policy_path).is_dir():
        return Path(policy_path)
    from huggingface_hub import snapshot_download

    return Path(snapshot_download(policy_path))


def save_with_phase_energy(
    policy, phase_energy: PhaseEnergy, source: Path, output_dir: Path, processors=()
) -> None:
    """`policy` with the fitted `phase_energy`, saved to `output_dir` as a checkpoint of `source`: its config's
    `phase_energy` set (and, with E_c on its own encoder, its failure check `success_energy`), the
    `processors` saved, and the source's other files copied but for its failure calibration."""
    policy.model.phase_energy = phase_energy.to(policy.config.device)
    policy.config.phase_energy = PhaseEnergyConfig(bins=phase_energy.bins, hidden=phase_energy.hidden)
    if policy.config.context_energy_on_own_encoder:
        policy.config.monitor.failure_score = PHASE_FITTED_FAILURE_SCORE
    output_dir.mkdir(parents=True, exist_ok=True)
    policy.save_pretrained(output_dir)
    for processor in processors:
        processor.save_pretrained(output_dir)
    for file in source.iterdir():
        if file.is_file() and file.name not in _NOT_COPIED and not (output_dir / file.name).exists():
            shutil.copy2(file, output_dir / file.name)


def run(cfg: FitPhaseEnergyConfig) -> Path:
    """Fits the phase energy and writes the new checkpoint folder; returns it."""
    cfg.validate()
    # Imported here so that `--help` stays fast.
    from lerobot.datasets import LeRobotDataset
    from lerobot.policies.factory import make_pre_post_processors

    from ..modeling_ebvla import EBVLAPolicy

    source = _source_folder(cfg.policy_path)
    policy = EBVLAPolicy.from_pretrained(source)
    if cfg.device is not None:
        policy.config.device = cfg.device
    policy.to(policy.config.device).eval()
    preprocessor, postprocessor = make_pre_post_processors(
        policy.config,
        pretrained_path=str(source),
        preprocessor_overrides={"device_processor": {"device": str(policy.config.device)}},
    )
    dataset = LeRobotDataset(cfg.dataset_repo_id, root=cfg.dataset_root)
    contexts = demonstration_contexts(policy, preprocessor, dataset, cfg.batch_size)
    logging.info(f"Pooled contexts of {len(contexts['features'])} demonstration frames.")

    phase_energy = PhaseEnergy(contexts["features"].shape[1], cfg.bins, cfg.hidden)
    fit = fit_phase_energy(phase_energy, **contexts, seed=cfg.seed)
    save_with_phase_energy(policy, phase_energy, source, cfg.output_dir, (preprocessor, postprocessor))
    summary = {"source": str(cfg.policy_path), "dataset": cfg.dataset_repo_id, **asdict(fit)}
    (cfg.output_dir / FIT_SUMMARY_FILENAME).write_text(json.dumps(summary, indent=1) + "\n")
    logging.info(
        f"Phase energy fitted for {fit.epochs} epochs on {fit.frames} frames of {fit.episodes} episodes (held-out "
        f"NLL {min(fit.validation_nll):.4f}); saved to {cfg.output_dir}."
    )
    return cfg.output_dir

"""Splits a joint-energy checkpoint's recorded final energy into the head's part and the context energy E_c.

For `energy_ood_margin_on="context"` checkpoints the recorded final energy is E(a^(K), C) + E_c(C); the records
hold each chunk's pooled context (`--record_context_features`), so E_c is recomputed from them and the head's part
is the difference. Prints, per condition, the first-3-chunk AUROC against the held-out vanilla rollouts of the
joint energy, the head's part and E_c, with bootstrap 95% intervals.

    python research/benchmarks/joint_energy_decompose.py CHECKPOINT RECORDS_FOLDER
"""

import sys
from pathlib import Path

import numpy as np
import torch

from lerobot_policy_ebvla import EBVLAPolicy
from lerobot_policy_ebvla.monitoring.metrics import auroc, bootstrap_auroc_interval
from lerobot_policy_ebvla.monitoring.records import group_by_episode, read_energy_records, records_file_in

CHUNKS = 3


def rollout_scores(policy: EBVLAPolicy, folder: Path) -> np.ndarray:
    """(episodes, 3): joint, head part, E_c, each the mean over the first chunks."""
    out = []
    for chunks in group_by_episode(read_energy_records(records_file_in(folder))).values():
        chunks = sorted(chunks, key=lambda r: r.chunk_index)[:CHUNKS]
        features = torch.tensor(np.stack([r.context_feature for r in chunks]), dtype=torch.float32)
        with torch.no_grad():
            context = policy.model.context_energy(features).numpy()
        final = np.array([r.final_energy for r in chunks])
        out.append((final.mean(), (final - context).mean(), context.mean()))
    return np.array(out)


def main() -> None:
    checkpoint, root = sys.argv[1], Path(sys.argv[2])
    policy = EBVLAPolicy.from_pretrained(checkpoint).eval()
    vanilla = rollout_scores(policy, root / "vanilla")
    print("| condition | joint | head part | E_c |")
    print("|---|---|---|---|")
    for folder in sorted(p for p in root.iterdir() if p.is_dir()):
        if folder.name in ("vanilla", "calibration", "vanilla_extra"):
            continue
        scores = rollout_scores(policy, folder)
        cells = []
        for j in range(3):
            low, high = bootstrap_auroc_interval(vanilla[:, j], scores[:, j])
            cells.append(f"{auroc(vanilla[:, j], scores[:, j]):.2f} [{low:.2f}, {high:.2f}]")
        print(f"| {folder.name} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()

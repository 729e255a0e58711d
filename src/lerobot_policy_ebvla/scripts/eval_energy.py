"""`ebvla-eval`: lerobot-eval that also records the energy of every action chunk the policy refines.

It takes lerobot-eval's arguments and runs LeRobot's own evaluation under the energy recorder
(`pipelines.eval_energy.eval_energy`). Alongside `eval_info.json` it writes `energy_records.jsonl`: one
`EnergyRecord` per episode and predicted chunk. `--restart_spread_chains=N`, `--normalized_energy_samples=N`
and `--record_context_features=true` also record the baselines of the OOD report (see
`monitoring/baselines.py`).

Example:

    MUJOCO_GL=egl ebvla-eval --policy.path=outputs/train/ebvla_reach/checkpoints/last/pretrained_model \\
        --env.type=metaworld_ebvla --env.task=reach-v3 --env.fast_render=true \\
        --env.perturbation=pose --env.perturbation_severity=3 \\
        --eval.n_episodes=10 --eval.batch_size=1 --output_dir=outputs/eval/reach_pose3 \\
        --restart_spread_chains=8 --record_context_features=true

Unlike lerobot-eval, which always renders videos of the first 10 episodes, videos are off unless
`--max_episodes_rendered` is set: rendering them doubles the cost of an env step.
"""

from lerobot.configs import parser
from lerobot.utils.import_utils import register_third_party_plugins
from lerobot.utils.utils import init_logging

from lerobot_policy_ebvla.pipelines.eval_energy import EnergyEvalPipelineConfig, eval_energy


@parser.wrap()
def eval_energy_main(cfg: EnergyEvalPipelineConfig) -> None:
    eval_energy(cfg)


def main() -> None:
    init_logging()
    register_third_party_plugins()
    eval_energy_main()


if __name__ == "__main__":
    main()

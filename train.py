"""Train an event keypoint network: ``python train.py model=superlite`` (see conf/ and README).

Thin by design: Hydra composes the config, :func:`aerovis_train.training.train` does the job and
returns the best validation AUC@10, which any Hydra sweeper can optimise (``-m``).
"""

import sys

import hydra
from omegaconf import DictConfig


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(cfg: DictConfig) -> float:
    from aerovis_slam.errors import DataError
    from aerovis_train.training import train

    try:
        return train(cfg)
    except DataError as exc:
        print(f"train.py: error: {exc}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()

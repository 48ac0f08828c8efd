#!/usr/bin/env python
"""Train the CAE on your own images: ``python train.py --images DIR [--config configs/train.yaml] [--out DIR]``.

A thin entry point; the logic lives in ``cae.train`` (usable from Python as ``cae.train.main(...)``).
"""

import sys

from cae.train import cli

if __name__ == "__main__":
    sys.exit(cli())

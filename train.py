#!/usr/bin/env python
"""Train the CAE on your own images: ``python train.py --images DIR [--config configs/train.yaml] [--out DIR]``.

A thin entry point, the same as ``cae-lcd train ...``; the logic lives in ``cae.train`` (usable from Python as
``cae.train.main(...)``) and the options in ``cae_lcd.cli.train``.
"""

import sys

from cae_lcd.cli.main import main

if __name__ == "__main__":
    sys.exit(main(["train", *sys.argv[1:]]))

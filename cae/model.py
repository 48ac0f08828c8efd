"""The convolutional autoencoder of Leonardi & Stahl (IFAC 2018), as the paper describes it, with one addition
that has no parameters: the input may be standardised per image (``input_norm``, below).

Shapes (B = batch):

    image  (B, 3, 256, 256) float in [0, 1]
      input_norm "standardise": each image brought to mean 0.5 and spread 0.25, clipped to [0, 1] (its light level
      and contrast removed: a night frame and a day frame of one place enter alike); "none": as given (the paper)
      Encoder: 4 x [conv 3x3 (32, 32, 32, 16 filters, zero padding) + ReLU + max-pool 2x2] (run pooled first: the
               same values, the ReLU on a quarter of them)
    code   (B, 16, 16, 16)  -> flattened (B, 4096), channel-major (C, H, W) order
      Decoder: 4 x [nearest-neighbour resize x2 + conv 3x3x32 + ReLU], then conv 3x3x3
    logits (B, 3, 256, 256)  (sigmoid at inference; the loss takes logits)

Weights are initialised from N(0, 0.05), biases at zero, as in the paper.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from cae_lcd.core.errors import ConfigError, ImageError

__all__ = ["Encoder", "Decoder", "ConvAutoencoder", "INPUT_SIZE", "CODE_SHAPE", "CODE_DIM", "INPUT_NORMS",
           "standardise", "MaxPool2x2"]

INPUT_SIZE = 256  #: side of the square network input, pixels
CODE_SHAPE = (16, 16, 16)  #: (channels, height, width) of the bottleneck
CODE_DIM = 16 * 16 * 16  #: length of the flattened code
INPUT_NORMS = ("none", "standardise")  #: what ``Encoder`` does to an image before its first layer
_MEAN, _SPREAD = 0.5, 0.25  #: a standardised image's mean and standard deviation (before clipping)


def standardise(x: torch.Tensor) -> torch.Tensor:
    """Each image of ``(B, C, H, W)`` in [0, 1] brought to mean 0.5 and standard deviation 0.25 over all its values,
    clipped to [0, 1]; a flat image becomes flat grey. Same shape and memory layout."""
    if x.shape[0] == 0:
        return x
    # image by image: the same sums whatever the batch (an image's code does not depend on its batch); in place
    # after one copy, which keeps the layout (0.2 ms an image on one core, against 1 ms for the broadcast expression)
    mean = torch.stack([image.mean() for image in x]).view(-1, 1, 1, 1)
    gain = 1.0 / (torch.stack([image.std() for image in x]).view(-1, 1, 1, 1) / _SPREAD + 1e-3)
    return torch.sub(x, mean).mul_(gain).add_(_MEAN).clamp_(0.0, 1.0)


class MaxPool2x2(nn.Module):
    """``nn.MaxPool2d(2)``, the same values faster where nothing is learned: ``(B, C, H, W) -> (B, C, H/2, W/2)``.

    Without autograd, on the CPU, a channels-last input of even sides is pooled by two elementwise maxima (rows, then
    columns: each output the largest of its four inputs, NaN kept, as ``max_pool2d`` gives), 0.26 ms against 0.71 for
    the encoder's first pool (32 x 256 x 256, one core); anything else goes to ``F.max_pool2d`` (training's gradient
    included). No parameters: a checkpoint's keys are those of ``nn.MaxPool2d``.
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        if torch.is_grad_enabled() or x.device.type != "cpu" or x.ndim != 4 or h % 2 or w % 2 \
                or not x.is_contiguous(memory_format=torch.channels_last):
            return F.max_pool2d(x, 2)
        rows = torch.maximum(x[:, :, 0::2], x[:, :, 1::2])
        return torch.maximum(rows[:, :, :, 0::2], rows[:, :, :, 1::2])


def _init(module: nn.Module, std: float = 0.05) -> None:
    for m in module.modules():
        if isinstance(m, nn.Conv2d):
            nn.init.normal_(m.weight, 0.0, std)
            nn.init.zeros_(m.bias)


class Encoder(nn.Module):
    """Image -> 4096-d code.

    Input ``(B, 3, 256, 256)`` float in [0, 1] (any other shape is refused: a 224x224 input gave a 3136-d code);
    output ``(B, 4096)`` of unit L2 norm, as ``cae.encode_images`` gives (an all-zero code stays zero);
    ``forward_map`` gives the code map before normalisation (what the decoder reads). Accepts channels-last input,
    which is faster on CPU.

    Args:
        input_norm: one of ``INPUT_NORMS``, what is done to each image first (saved in a checkpoint's conf;
            ``cae.load_encoder`` sets it from there).
        lowpass: Gaussian sigma, in an image's own pixels, that ``cae.preprocess`` reads an image smaller than the
            input through before bringing it up; 0 = none. Not applied here (the network sees 256x256 only): the
            weights' fact, saved in a checkpoint's conf as ``input_norm`` is.
    """

    filters = (32, 32, 32, 16)

    def __init__(self, input_norm: str = "none", lowpass: float = 0.0) -> None:
        super().__init__()
        if input_norm not in INPUT_NORMS:
            raise ConfigError(f"input_norm must be one of {', '.join(INPUT_NORMS)}; got {input_norm!r}")
        self.input_norm = input_norm
        self.lowpass = float(lowpass)
        layers: list[nn.Module] = []
        c_in = 3
        for c_out in self.filters:
            # pooled before the ReLU: the same values (max and ReLU commute) with the ReLU on a quarter of them;
            # the checkpoint keys are the same (the convolutions stay at 0, 3, 6, 9)
            layers += [nn.Conv2d(c_in, c_out, 3, padding=1), MaxPool2x2(), nn.ReLU(inplace=True)]
            c_in = c_out
        self.features = nn.Sequential(*layers)
        _init(self)

    def forward_map(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, 3, 256, 256)`` -> the code as a feature map ``(B, 16, 16, 16)``, not normalised.

        Raises:
            ImageError: an input of another shape (``cae.preprocess`` makes the network's input from any image).
        """
        if x.ndim != 4 or tuple(x.shape[1:]) != (3, INPUT_SIZE, INPUT_SIZE):
            raise ImageError(f"the encoder takes (B, 3, {INPUT_SIZE}, {INPUT_SIZE}) images; got {tuple(x.shape)} "
                             "(cae.preprocess or cae.encode_images make them from any image)")
        return self.features(self.network_input(x))

    def network_input(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, 3, 256, 256)`` in [0, 1] -> what the first layer reads (``input_norm``); the reconstruction's
        target."""
        return standardise(x) if self.input_norm == "standardise" else x

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, 3, 256, 256)`` -> codes ``(B, 4096)`` of unit L2 norm."""
        return F.normalize(self.forward_map(x).reshape(x.shape[0], -1), dim=1, eps=1e-12)


class Decoder(nn.Module):
    """Code map ``(B, 16, 16, 16)`` -> reconstruction logits ``(B, 3, 256, 256)``."""

    def __init__(self) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        c_in = CODE_SHAPE[0]
        for _ in range(4):
            layers += [nn.Upsample(scale_factor=2, mode="nearest"), nn.Conv2d(c_in, 32, 3, padding=1), nn.ReLU(inplace=True)]
            c_in = 32
        layers.append(nn.Conv2d(32, 3, 3, padding=1))
        self.layers = nn.Sequential(*layers)
        _init(self)

    def forward(self, code_map: torch.Tensor) -> torch.Tensor:
        return self.layers(code_map)


class ConvAutoencoder(nn.Module):
    """Encoder + decoder; ``forward`` returns reconstruction logits ``(B, 3, 256, 256)`` of the encoder's input
    (``Encoder.network_input``: the standardised image with ``input_norm`` "standardise")."""

    def __init__(self, input_norm: str = "none", lowpass: float = 0.0) -> None:
        super().__init__()
        self.encoder = Encoder(input_norm, lowpass)
        self.decoder = Decoder()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.decoder(self.encoder.forward_map(x))

    @torch.no_grad()
    def reconstruct(self, x: torch.Tensor) -> torch.Tensor:
        """Reconstruction in [0, 1] (sigmoid of the logits), ``(B, 3, 256, 256)``."""
        return torch.sigmoid(self(x))

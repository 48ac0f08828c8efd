"""The convolutional autoencoder (Leonardi & Stahl, IFAC 2018) and everything about it.

    >>> import cae
    >>> encoder = cae.load_encoder()                      # shipped weights, no download
    >>> codes = cae.encode_images(encoder, [img1, img2])  # (2, 4096), unit norm   # doctest: +SKIP
"""

from cae_lcd.core.errors import ConfigError, ImageError
from cae_lcd.core.images import read_image, to_gray_u8

from .encode import encode_images, normalize_codes
from .model import CODE_DIM, INPUT_SIZE, ConvAutoencoder, Decoder, Encoder
from .preprocess import preprocess
from .weights import DEFAULT_WEIGHTS, load_autoencoder, load_encoder

__all__ = ["Encoder", "Decoder", "ConvAutoencoder", "load_encoder", "load_autoencoder", "preprocess", "read_image",
           "to_gray_u8", "encode_images", "normalize_codes", "ConfigError", "ImageError", "CODE_DIM", "INPUT_SIZE",
           "DEFAULT_WEIGHTS"]
__version__ = "0.1.0"

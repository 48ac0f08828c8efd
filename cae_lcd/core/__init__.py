"""The base layer under every package: errors, configuration (merge, rules, registry), image reading and
conversion, atomic file writing and the command-line runner. Imports nothing from the project."""

from .conf import Registry, check_conf, configure, dump_conf, load_conf_file, merge_conf
from .errors import ConfigError, DatabaseError, ImageError, LCDError
from .images import IMAGE_EXTENSIONS, read_image, to_gray_u8, to_rgb_u8, to_uint8

__all__ = ["LCDError", "ConfigError", "ImageError", "DatabaseError", "Registry", "merge_conf", "check_conf",
           "configure", "load_conf_file", "dump_conf", "IMAGE_EXTENSIONS", "read_image", "to_gray_u8", "to_rgb_u8",
           "to_uint8"]

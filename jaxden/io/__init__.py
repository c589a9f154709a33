"""File I/O: multi-channel EXR frames and images."""

from jaxden.io.exr import read_frame, read_header, read_image, write_frame, write_image

__all__ = ["read_frame", "read_header", "read_image", "write_frame", "write_image"]

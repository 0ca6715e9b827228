"""Image files <-> arrays: EXR through OpenImageIO, RAW through rawpy (LibRaw); atomic writes.

The only package that touches image files, and it imports nothing of the job. Library errors
become :class:`InputError` naming the file.
"""

from .frames import (
                     ATTR_CFA,
                     ATTR_SATURATION,
                     EXR_SUFFIXES,
                     FRAME_SUFFIXES,
                     RAW_SUFFIXES,
                     FileStamp,
                     Frame,
                     FrameInfo,
                     find_frames,
                     kind_of,
                     stamp,
)
from .read import check_consistent, read_exr, read_exr_planes, read_frame, read_raw, read_stack
from .write import atomic_output, write_exr, write_text

__all__ = ["ATTR_CFA", "ATTR_SATURATION", "EXR_SUFFIXES", "FRAME_SUFFIXES", "RAW_SUFFIXES", "FileStamp", "Frame",
           "FrameInfo", "atomic_output", "check_consistent", "find_frames", "kind_of", "read_exr", "read_exr_planes",
           "read_frame", "read_raw", "read_stack", "stamp", "write_exr", "write_text"]

"""Direct Slicing Tessellation geometry core.

Pure: knows STEP, planes, section curves, meshes and reports. Imports no web framework and no queue.
The entry point is :func:`worker.dst.pipeline.slice_step`.
"""

from worker.dst.errors import DstError
from worker.dst.params import SliceParams

__all__ = ["DstError", "SliceParams"]

"""The geometry core's exceptions. Each carries a stable machine-readable ``code``."""


class DstError(Exception):
    """Base class of every error the core raises on purpose."""

    code = "dst_error"


class InvalidParameters(DstError):
    """A slicing parameter is outside its allowed range."""

    code = "invalid_parameters"


class StepReadError(DstError):
    """The file is not a readable STEP file (empty, truncated, another format, syntax errors)."""

    code = "step_read_error"


class EmptyGeometryError(DstError):
    """The STEP file was read but holds no geometry at all."""

    code = "empty_geometry"


class NotASolidError(DstError):
    """The geometry holds no closed solid, even after sewing."""

    code = "not_a_solid"


class TessellationError(DstError):
    """The DST mesh could not be built to its guarantees (the message says which one failed)."""

    code = "tessellation_error"


class UnmeshedFaceError(TessellationError):
    """OCCT's mesher gave a face (larger than the mesh tolerance) no triangles at all."""


class ResourceLimitExceeded(DstError):
    """The job would exceed a configured limit (planes, triangles, memory)."""

    code = "resource_limit"


class MeshReadError(DstError):
    """A mesh file to be measured is not a readable STL or holds no triangles."""

    code = "mesh_read_error"

"""Tolerances and limits of the geometry core, each with its unit and the reason for its value."""

# --- parameter ranges (validated at the boundary, trusted inside) -----------------------------------
LAYER_HEIGHT_RANGE_MM = (0.01, 2.0)  # FFF/resin printers print between ~0.01 and ~1.2 mm layers
SEGMENT_LENGTH_RANGE_MM = (0.01, 50.0)  # below 10 um the STL is larger than any slicer keeps
CHORD_ERROR_RANGE_MM = (0.0001, 1.0)  # 0.1 um is far below float32 resolution on a 100 mm part
MAX_PLANES = 20_000  # 4 m of 0.2 mm layers; beyond that the job is certainly a unit mistake
MAX_TRIANGLES = 20_000_000  # a 1 GB binary STL; no slicer loads more in reasonable time
# (triangle, plane) pairs a topology mesh's cut may hold: the cut takes ~400 bytes a pair at its peak
# (bug29241 turned: 1.4 million pairs, 0.57 GB), so 10 million is ~4 GB; 11752 turned (37, -61, 113)
# at 0.3 mm layers has 45 million (3865 planes across 158k triangles) and took 24 GB before it was killed
MAX_SECTION_PAIRS = 10_000_000

# --- exactness -------------------------------------------------------------------------------------
LEVEL_TOL_MM = 1e-10  # a ring vertex's |z - plane| after Newton: far below float32 (1e-6 at 10 mm)
NEWTON_MAX_ITER = 40  # Newton on a level set converges in 3-6 steps from a mesh seed; 40 is a fence
ROOT_XTOL = 1e-14  # Brent tolerance on normalised parameters along a mesh edge or curve span

# --- the topology mesh -----------------------------------------------------------------------------
# The coarse BRepMesh only supplies topology (which section loops exist and how they connect) and
# seeds for Newton; ring vertices never come from it. Its deflection is relative to the part size
# with an absolute cap, so that loops larger than ~sqrt(8 R d) are never missed.
TOPO_DEFLECTION_REL = 2e-4  # of the bounding-box diagonal
TOPO_DEFLECTION_MAX_MM = 0.02
TOPO_DEFLECTION_MIN_MM = 0.001
TOPO_ANGULAR_RAD = 0.35  # ~20 deg: keeps curved faces resolved where the linear bound is loose
# a solid whose BRepMesh mesh fails (a face unmeshed, the mesh not closed) is meshed again this much
# finer, in turn, until one holds (BRepMesh's failures can come and go with the deflection alone)
TOPO_RETRY_FINER = (0.7, 0.5)
POLE_TOL_MM = 1e-7  # a side of a face's (u, v) box whose iso-line is this short is a pole (an apex)
# ring points closer than this in x, y and z are one (a ring drops the repeat: ``sampling._dedupe_cyclic``;
# a run's samples drop theirs: ``RunRefiner._sample_runs``; a pinned loop's crossings that close share
# their vertex first: ``Crossings._merge_coincident``)
REPEAT_MM = 1e-9
MERGE_TOL_REL = 1e-9  # of the bbox diagonal: nodes of different faces closer than this are one node
T_JUNCTION_TOL_MM = 1e-7  # a vertex this near an open edge of the DST mesh is a T-junction on it

# --- sampling --------------------------------------------------------------------------------------
SEGMENT_FILL = 0.97  # aim segments at 97% of the budget: Newton moves points by up to ~1% of a span
MIN_LOOP_VERTICES = 3  # a closed loop needs at least a triangle
MAX_SUBDIVISION = 64  # per segment and pass; a segment needing more is split recursively

# --- reporting -------------------------------------------------------------------------------------
ON_PLANE_TOL_MM = 1e-6  # a flat face this close to a plane is "on" it for a float32 slicer
CURA_MAX_DEVIATION_MM = 0.025  # Cura meshfix_maximum_deviation default
CURA_MAX_RESOLUTION_MM = 0.5  # Cura meshfix_maximum_resolution default
PRUSA_GCODE_RESOLUTION_MM = 0.0125  # PrusaSlicer gcode_resolution default

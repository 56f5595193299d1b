"""Trace delineation on photographs (issue 3): one function per stage, each returning its intermediate.

denoise → phase_congruency (or phase_congruency_mono) → detect_edges (with line_filter's lines) →
find_segments → grow_traces (→ dropped along the mesh's `silhouette`) → label_components; `autotrace` runs
them all with a `DelineationParams`. Across photos, `supported_traces` keeps the segments a photo turned down
where the other photos' traces show them, and `carried_traces` adds the other photos' traces a photo
sees but has not traced where its own edges lie along them. Guided manual traces:
`spline_curve`, and `least_cost_curve` on a `trace_cost` of phase congruency or `darkness`.
Pixel convention: (0, 0) is the centre of the top-left pixel, u = column, v = row.
"""

from engine.delineate.components import label_components, trace_map
from engine.delineate.denoise import denoise
from engine.delineate.edges import EdgeMap, detect_edges, non_maximum_suppression
from engine.delineate.grow import grow_traces
from engine.delineate.guided import darkness, least_cost_curve, spline_curve, trace_cost
from engine.delineate.line_filter import LineMap, line_filter
from engine.delineate.params import DelineationParams, params_from_dict, read_params, write_params
from engine.delineate.phase import PhaseCongruency, phase_congruency, phase_congruency_mono
from engine.delineate.pipeline import AutoTrace, autotrace, read_photo
from engine.delineate.segments import Segments, find_segments
from engine.delineate.silhouette import silhouette
from engine.delineate.support import carried_traces, kinds_traced_elsewhere, supported_traces

__all__ = ["AutoTrace", "DelineationParams", "EdgeMap", "LineMap", "PhaseCongruency", "Segments", "autotrace",
           "carried_traces", "kinds_traced_elsewhere",
           "darkness", "denoise", "detect_edges", "find_segments", "grow_traces", "label_components",
           "least_cost_curve", "line_filter", "non_maximum_suppression", "params_from_dict", "phase_congruency", "phase_congruency_mono",
           "read_params", "read_photo", "silhouette", "spline_curve", "supported_traces", "trace_cost", "trace_map", "write_params"]

"""The pose methods: the one registry of what a graph can estimate, which node produces it, how it
is drawn, which one leads, and the paper's figure for it.

Every list of methods in the project (the pose nodes' outputs, the evaluator's and monitor's
inputs, the evaluation's tables, the viewer's colours, the graphs ``needletrack eval`` runs) is
derived from ``REGISTRY``; add a method here and everything that lists methods knows it. Imports
nothing, so every package may use it.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class PoseMethod:
    """One way to estimate ``T_ecm_needle``.

    ``output``: the node output that publishes it in the graphs ``needletrack eval`` runs
    (``node/output``); ``colour``: its hex colour in figures and the viewer (``common.palette``: the rest); ``rank``:
    lower leads (the final output is the first present); ``fuses``: the single-frame method a
    multi-view method fuses (None: a single-frame method); ``needs``: the other methods whose poses
    it takes (a filter over time needs what it filters); ``always_reported``: in every
    ``results.json`` (the paper's Table III and ``pnp_joint``), else only when produced;
    ``paper``: the paper's (mean mm, mean deg), Table III, where it has one; ``label``: what it
    is, in a few words, for tables."""
    name: str
    output: str
    colour: str
    rank: int
    fuses: str | None = None
    needs: tuple[str, ...] = ()
    always_reported: bool = False
    paper: tuple[float, float] | None = None
    label: str = ""

    @property
    def multiview(self) -> bool:
        return self.fuses is not None


REGISTRY = (
    PoseMethod("pnp_average", "epnp_average/pose", "#1f77b4", 5, always_reported=True, paper=(2.26, 6.74),
               label="Pipeline I: EPnP per camera, averaged"),
    PoseMethod("pnp_joint", "epnp_joint/pose", "#ff7f0e", 4, always_reported=True,
               label="one pose fitted in both cameras"),
    PoseMethod("triangulation", "triangulate/pose", "#9467bd", 6, always_reported=True, paper=(6.13, 35.61),
               label="Pipeline II: DLT triangulation and Arun's registration"),
    PoseMethod("multiview", "fusion/pose", "#d62728", 3, fuses="pnp_joint", always_reported=True,
               paper=(1.76, 8.55), label="fusion of pnp_joint over the endoscope's poses"),
    PoseMethod("refined", "refine/pose", "#17becf", 1, label="dense arc fit, with a covariance"),
    PoseMethod("multiview_refined", "fusion_refined/pose", "#8c564b", 2, fuses="refined",
               label="fusion of refined poses"),
    PoseMethod("tracked", "tracker/pose", "#ff00ff", 0, needs=("refined",),
               label="refined poses filtered over time: at rest, in the jaws, free"),
)
BY_NAME = {m.name: m for m in REGISTRY}

POSE_METHODS = tuple(m.name for m in REGISTRY)
"""Every method's name, in the registry's order (the input names of nodes that take them all)."""
REPORTED_METHODS = tuple(m.name for m in REGISTRY if m.always_reported)
"""The methods every ``results.json`` reports."""
EXTRA_METHODS = tuple(m.name for m in REGISTRY if not m.always_reported)
"""Reported beside ``REPORTED_METHODS`` when the graph produced them."""
MULTIVIEW_METHODS = frozenset(m.name for m in REGISTRY if m.multiview)
FINAL_ORDER = tuple(m.name for m in sorted(REGISTRY, key=lambda m: m.rank))
"""Which method leads: the first of these that is present is the final output."""
METHOD_COLOURS = {m.name: m.colour for m in REGISTRY}
POSE_OUTPUTS = {m.name: m.output for m in REGISTRY}
METHOD_NEEDS = {m.name: ((m.fuses,) if m.fuses else ()) + m.needs for m in REGISTRY if m.fuses or m.needs}
"""The methods each method takes poses from (what it fuses first), where it takes any."""
PAPER_POSE = {m.name: m.paper for m in REGISTRY if m.paper}

TRACK_MODES = ("rest", "held", "free")
"""The ``tracked`` method's modes, what its poses state (``PoseEstimate.mode``): the needle at
rest in the world, held in an instrument's jaws, free and moving (docs/tracking.md)."""


def requires(name: str) -> set[str]:
    """Every method ``name`` takes poses from, directly or through another (``METHOD_NEEDS``)."""
    found: set[str] = set()
    todo = list(METHOD_NEEDS.get(name, ()))
    while todo:
        m = todo.pop()
        if m not in found:
            found.add(m)
            todo += METHOD_NEEDS.get(m, ())
    return found


def final_method(present) -> str | None:
    """The method that leads among ``present`` (names): the first of ``FINAL_ORDER``; a name
    not in the registry only when nothing registered is present; None when empty."""
    present = list(present)
    return next((m for m in FINAL_ORDER if m in present), present[0] if present else None)


def in_final_order(present) -> list[str]:
    """``present`` (names) in ``FINAL_ORDER``, names not in the registry after, as given."""
    present = list(present)
    return [m for m in FINAL_ORDER if m in present] + [m for m in present if m not in BY_NAME]


def last_stage(present) -> str | None:
    """The method at the pipeline's end among ``present`` (names): multi-view methods (they
    fuse the others) first, each group in ``FINAL_ORDER``; None when none is registered."""
    present = set(present)
    order = [m for m in FINAL_ORDER if m in MULTIVIEW_METHODS] + \
            [m for m in FINAL_ORDER if m not in MULTIVIEW_METHODS]
    return next((m for m in order if m in present), None)

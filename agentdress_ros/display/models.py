"""What the node publishes for display, on top of its garment models (ROS-free): no skin through the cloth, garments
layered, a smooth mesh.

`dress_for_display(models, body, layers, subdivision)` takes the node's models ({name: GarmentModel}, "body"
included when it is published) and returns them ready for display, inner layers first:
- the body without the faces its garments cover (agentdress_ros.garment.coverage) where they hang at rest, deep
  inside their open edges, and without the faces under cloth over a range of poses and shapes (always_covered:
  computed once per set of garments, nothing per frame); the band it keeps under their edges sinks under the cloth
  (at rest, so it costs nothing per frame);
- each garment pushed out of the garment of the next lower layer (agentdress_ros.engine.layering), through a
  binding made once per shape, between the two garments as they hang at the rest pose on that shape (vertex ids
  and weights follow every pose: both garments follow the body), and lifted where a vertex of the lower garment
  would pass between its vertices (the reverse binding);
- each garment refined by `subdivision` rounds of Loop subdivision (agentdress_ros.engine.subdivision), after the
  engine's penetration handling and the layering;
- when the body is drawn, each garment's band along its open edges pushed off the skin as posed this frame
  (agentdress_ros.engine.skin_clearance): the drawn skin there would show through the cuffs and hems in a saw-tooth;
  before it, each refined garment's open edges are smoothed along their arc length as posed this frame (a pose can
  bunch a cuff into a bump), and after it each edge vertex takes the largest of its neighbours' pushes faded along
  the edge, so that a vertex pushed alone makes a smooth bump, not a tooth (engine.subdivision).
Coverage and subdivision matrices are cached per topology (a shape change reuses them), layer and skin bindings per
topology and shape.
"""
from __future__ import annotations

import time

import numpy as np

from ..body import REFERENCE_SHAPE
from ..engine.layering import (TRACK_STEPS, LayerBinding, bind_layers, bind_to_vertices, bind_under, lift_over_inner,
                               push_out_of_inner, track_nearest, vertex_neighbours)
from ..engine.skin_clearance import EDGE_CLEARANCE, bind_edges_to_skin, push_off_skin
from ..engine.subdivision import BoundaryLoops, LoopSubdivision, smooth_posed_boundaries, spread_edge_moves
from ..garment.binding import face_normals, vertex_normals
from ..garment.coverage import MAX_GAP, boundary_distance, cover_depth, faces_with_vertices, sloped, tuck_depth
from ..models.garment_models import BodyModel

__all__ = ["POSE_RANGE", "TEMPLATE_LAYERS", "CoveredBodyModel", "DisplayModel", "always_covered", "dress_for_display",
           "garment_rest", "pose_range", "shape_range"]

#: Layer of each template, inside out: trousers under a shirt worn outside them. A higher layer is pushed out of
#: the next lower one; equal layers are not layered. Tucked in: give the trousers a layer above the shirt's.
TEMPLATE_LAYERS = {"trousers": 1, "tshirt": 2, "longsleeve": 2}
#: The range of poses over which body faces always under a garment are hidden too (pose_range, always_covered).
POSE_RANGE = ("walk",)
POSE_STEP = 3
#: Footprint faces this far inside a garment's open edges (geodesically, at rest) are hidden without being checked
#: over the pose and shape ranges: a collar or a hem moves, the middle of a panel stays on the body.
EDGE_BAND = 0.03
#: The others stay hidden only under cloth this far inside its open edges in every pose and shape of the ranges:
#: looking down into a collar that stands off the neck shows the skin a few centimetres under it.
CHECK_BAND = 0.05
#: The sink changes by at most this much per metre over the skin (coverage.sloped): where the closest cloth of two
#: neighbouring neck vertices lies on either side of a collar, one sank 1.5 cm and the other not, a crease.
SLOPE = 0.5
_CACHE: dict = {}
_CACHE_SIZE = 32
_SHAPE_CACHE: dict = {}  # per shape: kept apart, so that shapes coming and going never evict a topology's entries


def _cached(key, make, cache=_CACHE):
    if key not in cache:
        if len(cache) >= _CACHE_SIZE:
            cache.pop(next(iter(cache)))
        cache[key] = make()
    return cache[key]


def _base(model):
    return model.base if isinstance(model, DisplayModel) else model


def _topology_key(model) -> tuple:
    base = _base(model)
    return (base.name, base.kind, base.n_vertices, str(getattr(base, "path", "")), hash(base.faces.tobytes()))


def _drape_key(model) -> tuple:
    """What decides how a model drapes, beyond its topology: its class and engine settings. Coverage and the layer
    and skin bindings are made from the model's own rest drape, so two models of one database with other pose
    models (a crowd tier's examples, Santesteban's) must not share them."""
    base = _base(model)
    return _topology_key(model) + (type(base).__name__, repr(getattr(getattr(base, "engine", None), "config", None)))


def garment_rest(model, body) -> np.ndarray:
    """The garment (V, 3) of a model at rest on the reference shape: a database's skinning rest, or the template
    fitted by its binding."""
    base = _base(model)
    engine = getattr(base, "engine", None)
    if engine is not None:
        rest = np.empty(engine.db.rest.shape, dtype=np.float64)
        rest[engine.order] = engine.db.rest  # the engine stores vertices sorted by region; output order here
        return rest
    if getattr(base, "db", None) is not None:  # a database model in the file's vertex order (Santesteban's)
        return np.asarray(base.db.rest, dtype=np.float64)
    return base.garment.rest_vertices(body, body.shape(REFERENCE_SHAPE))


def _draped_rest(model, body) -> np.ndarray:
    """The garment (V, 3) as the model dresses the rest pose (a database's drape, not its skinning rest: the layers
    are bound where the cloth actually hangs). Leaves no frame history behind."""
    out = np.array(model.synthesize(np.zeros((body.n_bones, 3)), np.zeros(3)), dtype=np.float64)
    model.reset()
    return out


def _layer_bindings(outer, inner, body, outer_refine=None, inner_refine=None):
    """(the outer garment's vertices bound to the inner garment, the inner garment's bound under the outer one,
    the refined outer's vertices bound to the refined inner's (None unless both are refined)), all as the two hang
    at the rest pose."""
    outer_rest, inner_rest = _draped_rest(outer, body), _draped_rest(inner, body)
    fine = None
    if outer_refine is not None and inner_refine is not None:
        fine = bind_to_vertices(outer_refine.apply(outer_rest).copy(), inner_refine.apply(inner_rest))
    return (bind_layers(outer_rest, inner_rest, inner.faces),
            bind_under(inner_rest, outer_rest, outer.faces), fine)


class CoveredBodyModel(BodyModel):
    """The body without the faces garments cover; the band kept under their edges sinks `sink` (hm08 (N,) metres)
    along the rest normals of each shape."""

    def __init__(self, body, beta, keep_faces: np.ndarray, sink: np.ndarray, covered_by: tuple):
        self.sink, self.covered_by = sink, covered_by
        super().__init__(body, beta)
        self.faces = np.ascontiguousarray(self.faces[keep_faces])

    def _rest_for(self, shape):
        normals = vertex_normals(shape.vertices, self.body.body_faces)
        return (shape.vertices - self.sink[:, None] * normals)[self.body_ids]


def _reference_drape(model, body) -> np.ndarray:
    """The garment (V, 3) as the model dresses the rest pose on the reference shape (a twin: `model` keeps its own
    shape and history)."""
    twin = _base(model).clone()
    twin.set_shape(REFERENCE_SHAPE)
    return _draped_rest(twin, body)


def _coverage(model, body):
    """(sink (N,), cover_depth (N,)) of one garment model over the hm08 vertices (cached): the footprint of
    the cloth where it hangs at rest, not of its skinning rest (a database's T-shirt collar drops 8-12 cm at the
    front from one to the other, and the neck it leaves would be drawn open)."""

    def make():
        shape = body.shape(REFERENCE_SHAPE)
        depth = cover_depth(shape.vertices, body.body_faces, _reference_drape(model, body), _base(model).faces)
        return tuck_depth(depth), depth

    return _cached(("coverage",) + _drape_key(model), make)


class DisplayModel:
    """A garment model under the same protocol, its output pushed out of an inner garment and refined for display.

    `coarse` is the last output before refinement (what an outer layer is pushed out of). `skin` (a SkinBinding of
    the output's edge band to the drawn body `skin_body`, a CoveredBodyModel on the same shape) keeps the edges off
    the skin."""

    def __init__(self, base, subdivision: LoopSubdivision | None = None, inner=None, binding=None, under=None,
                 fine=None, skin=None, skin_body=None):
        self.base, self.subdivision, self.inner, self.binding, self.under = base, subdivision, inner, binding, under
        # the refined outer bound to the refined inner (pushed out of it again after refinement), its inner vertices
        # this model's own: they follow the inner garment frame by frame
        self.fine = fine if fine is None else LayerBinding(fine.outer, fine.triangles.copy(), fine.barycentric,
                                                           fine.faces)
        self.skin, self.skin_body = skin, skin_body
        self.name, self.kind = base.name, base.kind
        self.faces = subdivision.faces if subdivision is not None else base.faces
        # the unrefined faces of this garment and of the inner one (the base may draw refined faces of its own)
        self.coarse_faces, self.inner_faces = base.faces, inner.coarse_faces if inner is not None else None
        self._inner_key = _topology_key(inner.base) if inner is not None else None
        self.coarse = self.refined = None
        self._fine_normals = self._out = None
        self._tracked = False  # whether the fine binding has followed a frame yet
        self._adjacency = None  # the refined inner garment's vertex neighbours (CSR), for the fine binding's walk
        self.layer_ms = self.refine_ms = self.skin_ms = 0.0  # cost of the last frame's layering, refinement, edges
        self._pushed = np.empty((base.n_vertices, 3), dtype=np.float32)
        self._normals = None
        self._loops = _cached(("boundary loops",) + _topology_key(base) + (len(self.faces),),
                              lambda: BoundaryLoops(self.faces)) if subdivision is not None else None
        self._before_push = None  # the refined frame before the edge push (the spread measures the push from it)
        if under is not None:  # the reverse binding's buffers: this garment's normals and lift
            self._own_normals = np.empty((base.n_vertices, 3), dtype=np.float32)
            self._lift = np.empty(base.n_vertices, dtype=np.float32)

    def __getattr__(self, name):  # engine, path, garment, shape_limits, ... of the wrapped model
        if name == "base":
            raise AttributeError(name)
        return getattr(self.base, name)

    @property
    def n_vertices(self) -> int:
        return self.subdivision.n_vertices if self.subdivision is not None else self.base.n_vertices

    def set_shape(self, beta) -> bool:
        return self.base.set_shape(beta)

    def reset(self) -> None:
        self.base.reset()
        self.forget_motion()

    def forget_motion(self) -> None:
        """A cut in the motion: the next frame may lie far from this one (the fine binding walks as far again)."""
        self._tracked = False

    def clone(self):
        return DisplayModel(self.base.clone(), self.subdivision)  # rewired by dress_for_display

    def synthesize(self, rotvecs, root_translation) -> np.ndarray:
        coarse = self.base.synthesize(rotvecs, root_translation)
        start = time.perf_counter()
        inner = self.inner.coarse if self.inner is not None else None
        if inner is not None and self.binding is not None and len(self.binding):
            np.copyto(self._pushed, coarse)
            coarse = self._pushed
            if self._normals is None or len(self._normals) != len(inner):
                self._normals = np.empty((len(inner), 3), dtype=np.float32)
            push_out_of_inner(coarse, inner, self.inner_faces, self.binding, normals=self._normals)
            if self.under is not None:
                lift_over_inner(coarse, self.coarse_faces, inner, self.under, normals=self._own_normals,
                                lift=self._lift)
        middle = time.perf_counter()
        self.coarse = coarse
        out = coarse
        # into a buffer of this model's own: the subdivision's is shared per topology, the base's is the engine's
        if self.subdivision is not None or (self.skin is not None and out is not self._pushed):
            refined = self.subdivision.apply(coarse) if self.subdivision is not None else coarse
            if self._out is None or self._out.shape != refined.shape or self._out.dtype != refined.dtype:
                self._out = np.empty_like(refined)
            out = self._out
            np.copyto(out, refined)
        fine_inner = self.inner.refined if self.inner is not None else None
        if self.fine is not None and fine_inner is not None and len(self.fine):
            # Loop smooths the two layers differently (the shirt's wide triangles over the waistband's bulge): the
            # refined shirt would dip under the refined trousers in slits 4 cm wide
            if self._fine_normals is None or len(self._fine_normals) != len(fine_inner):
                self._fine_normals = np.empty((len(fine_inner), 3), dtype=fine_inner.dtype)
            if self._adjacency is None:  # looked up once, not per frame (the key hashes the faces)
                self._adjacency = _cached(("adjacency", len(fine_inner)) + self._inner_key,
                                          lambda: vertex_neighbours(self.inner.faces, len(fine_inner)))
            # the binding was made at rest: its first frame walks as far as the pose carried the layers apart
            track_nearest(out, fine_inner, self.fine, self._adjacency, steps=TRACK_STEPS if self._tracked else 64)
            self._tracked = True
            push_out_of_inner(out, fine_inner, self.inner.faces, self.fine, normals=self._fine_normals)
        if self._loops is not None:
            # the drawn edges smoothed along their arc length as posed: a pose can bunch a cuff into a bump that the
            # smoothing at rest cannot see
            smooth_posed_boundaries(out, self._loops)
        refined = time.perf_counter()
        if self.skin is not None:
            transforms, _ = self.skin_body.body.pose(self.skin_body.shape, rotvecs, root_translation)
            if self._loops is not None:
                if self._before_push is None or self._before_push.shape != out.shape:
                    self._before_push = np.empty_like(out)
                np.copyto(self._before_push, out)
            push_off_skin(out, self.skin, transforms)
            if self._loops is not None:  # a vertex pushed alone would make a tooth: its edge neighbours follow
                spread_edge_moves(out, self._before_push, self._loops)
        self.refined = out
        end = time.perf_counter()
        self.layer_ms, self.refine_ms, self.skin_ms = 1e3 * (middle - start), 1e3 * (refined - middle), 1e3 * (
            end - refined)
        return out


def dress_for_display(models: dict, body, layers: dict | None = None, subdivision: int = 0, beta=None,
                      edge_clearance: bool = True) -> dict:
    """The node's models {name: model} ready for display (see the module docstring), ordered inner layers first and
    the body last. layers: {garment: layer} overriding TEMPLATE_LAYERS; subdivision: 0, 1 or 2 rounds; beta: the
    shape the models are fitted to (the layer and skin bindings are made per shape); edge_clearance: keep the
    garments' edges off the body when it is among the models."""
    shape_key = tuple(np.asarray(beta, dtype=np.float64).ravel().tolist()) if beta is not None else None
    layer_of = dict(TEMPLATE_LAYERS, **(layers or {}))
    garments = {n: _base(m) for n, m in models.items() if n != "body"}
    order = sorted(garments, key=lambda n: layer_of.get(n, 0))  # stable: equal layers keep their order
    layered = len({layer_of.get(n, 0) for n in order}) > 1  # every garment then keeps its `coarse` output
    out = {}
    for position, name in enumerate(order):
        base = garments[name]
        refine = None
        if subdivision:
            refine = _cached(("loop", subdivision) + _topology_key(base),
                             lambda: LoopSubdivision(base.faces, base.n_vertices, subdivision,
                                                     rest=garment_rest(base, body)))
        inner = next((out[n] for n in reversed(order[:position]) if layer_of.get(n, 0) < layer_of.get(name, 0)),
                     None)
        binding = under = fine = None
        if inner is not None:
            binding, under, fine = _cached(
                ("layer", shape_key, subdivision) + _drape_key(base) + _drape_key(inner),
                lambda: _layer_bindings(base, inner.base, body, refine, inner.subdivision), _SHAPE_CACHE)
        out[name] = DisplayModel(base, refine, inner, binding, under, fine) if refine is not None or layered else base
    if "body" in models:
        covered = out["body"] = _covered_body(models["body"], garments, body)
        if edge_clearance and EDGE_CLEARANCE > 0:
            body_shape = tuple(np.asarray(covered.shape.beta, dtype=np.float64).ravel().tolist())
            for name in order:
                model = out[name]
                if not isinstance(model, DisplayModel):  # its output is changed: a display model owns the buffer
                    model = out[name] = DisplayModel(model)
                model.skin_body = covered
                model.skin = _cached(("skin", body_shape, subdivision) + _drape_key(model) + covered.covered_by,
                                     lambda: _skin_binding(model, covered, body), _SHAPE_CACHE)
    return out


def _skin_binding(model: DisplayModel, covered: CoveredBodyModel, body):
    """The edge band of a display model's output, as the garment hangs at rest on its shape, bound to the drawn
    body's vertices on the same shape."""
    rest = _draped_rest(model.base, body)
    if model.subdivision is not None:
        rest = model.subdivision.apply(rest.astype(np.float32)).astype(np.float64)
    skin = np.asarray(covered.rest, dtype=np.float64)
    drawn = np.unique(covered.faces)  # a hidden face's vertices are not seen: nothing to keep the cloth off
    normals = vertex_normals(skin, covered.faces)
    bones, weights = covered.skin_binding()[1:]
    return bind_edges_to_skin(rest, boundary_distance(rest, model.faces), skin[drawn], normals[drawn], bones[drawn],
                              weights[drawn])


def pose_range(motions=POSE_RANGE, every: int = POSE_STEP):
    """(P, B, 3) rotation vectors: every `every`-th frame of one period of each procedural motion at 30 fps."""
    from ..motion.procedural import make_motion

    return np.concatenate([make_motion(name, fps=30.0).rotvecs[::every] for name in motions])


def shape_range() -> np.ndarray:
    """(S, 6) the shapes body faces are hidden over: the reference shape and the outer training levels of each
    training phenotype (body.training_shapes), where a garment sits loosest and tightest."""
    from ..body.training_shapes import training_shapes

    shapes = training_shapes()
    return np.concatenate([shapes[:1], shapes[1:].reshape(-1, 4, 6)[:, [0, 3]].reshape(-1, 6)])


def always_covered(garments, body, poses, hidden=None, shapes=None) -> np.ndarray:
    """(F,) bool over body.body_faces: the faces that lie under a garment - cloth over their centre, along their
    normal, within MAX_GAP and at least CHECK_BAND inside its open edges (coverage.cloth_over) - in every pose (P, B, 3)
    on every shape (S, 6) (default: the reference shape). Hiding them opens no gap over that range: where such a
    face pokes out of its garment, the cloth is right over it. garments: models (cloned here, the given ones are not
    touched); hidden (F,): faces not checked (left False)."""
    from ..garment.coverage import cloth_over

    shapes = np.asarray([REFERENCE_SHAPE] if shapes is None else shapes, dtype=np.float64)
    if len(poses) == 0 or len(shapes) == 0:
        return np.zeros(len(body.body_faces), dtype=bool)
    twins, edges = [], []
    for garment in garments:
        twin = _base(garment).clone()
        twins.append(twin)
        edges.append(boundary_distance(garment_rest(twin, body), twin.faces))
    plain = BodyModel(body, shapes[0])
    candidates = np.flatnonzero(~hidden) if hidden is not None else np.arange(len(plain.faces))
    root = np.zeros(3)
    for k, shape in enumerate(shapes):
        if k:  # the first is the one it was made on
            plain.set_shape(shape)
        for twin in twins:
            twin.set_shape(shape)
            twin.reset()
        for rotvecs in poses:
            skin = np.asarray(plain.synthesize(rotvecs, root), dtype=np.float64)
            centres = skin[plain.faces[candidates]].mean(axis=1)
            directions = face_normals(skin, plain.faces[candidates])
            covered = np.zeros(len(candidates), dtype=bool)
            for twin, edge in zip(twins, edges):
                cloth = np.asarray(twin.synthesize(rotvecs, root), dtype=np.float64)
                open_ = np.flatnonzero(~covered)  # each face against the next garment only while none covers it
                covered[open_] = cloth_over(centres[open_], directions[open_], cloth, twin.faces, MAX_GAP,
                                            CHECK_BAND, edge)
            candidates = candidates[covered]
    out = np.zeros(len(plain.faces), dtype=bool)
    out[candidates] = True
    return out


def _covered_body(model, garments: dict, body):
    key = tuple(sorted(_drape_key(g) for g in garments.values()))
    if getattr(model, "covered_by", None) == key:
        return model
    deep = np.zeros(len(body.body_faces), dtype=bool)
    sink = np.zeros(len(body.assets.template))
    for garment in garments.values():
        tuck, depth = _coverage(garment, body)
        deep |= faces_with_vertices(body.body_faces, depth >= EDGE_BAND)
        sink = np.maximum(sink, tuck)
    # the footprint's faces near an open edge (where a collar or a hem moves off the skin), and any other face, are
    # hidden where they lie under cloth in every pose of the range on every shape of the range
    hidden = deep | _cached(("posed",) + key, lambda: always_covered(list(garments.values()), body, pose_range(),
                                                                       deep, shape_range()))
    sink = sloped(sink, body.shape(REFERENCE_SHAPE).vertices, body.body_faces, SLOPE)
    return CoveredBodyModel(body, model.shape.beta, ~hidden, sink, key)


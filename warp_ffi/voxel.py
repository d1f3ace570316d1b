"""Voxel occupancy fractions of a triangle mesh on a Warp BVH (no gradient).

Inputs arrive validated (no checks here): float32 vertices ``(V, 3)``, flat in-range int32
indices ``(3 F,)``, and ``params`` = (origin x, y, z, voxel size, winding threshold, winding
accuracy, mesh-box centre x, y, z, mesh-box half diagonal), float32. Output: ``(nz, ny, nx)``
float32 fractions, ``nz * ny * nx < 2**31``.

1. One thread per triangle marks the voxels its bounding box meets (the reference's
   conservative overlap test, slightly widened against rounding; only the value 1 is ever
   written, so concurrent writes cannot conflict).
2. One thread walks one grid row along x. An unmarked voxel takes the inside/outside state of
   its centre; a marked one the stratified Monte-Carlo mean over its samples (the same positions
   as the JAX path: ``sample_jitter``).

Every inside test compares a winding number with ``params[4]`` (0.5 for closed meshes), as in
the JAX path: Warp's fast winding number (``mesh_query_point_sign_winding_number``, mesh built
with ``support_winding_number=True``), or in closed mode an integer count (below). The
angle-weighted pseudo-normal sign used before answered "outside" at the exact centre of a
sphere, where many faces are equally close, and near self-intersections. Queries use a radius
that always reaches the mesh (the distance to the mesh-box centre plus its half diagonal), so a
grid window deep inside a mesh reads as inside, unlike the reference's
``voxel_size * max(grid_dims)`` radius.

Closed meshes. Away from the surface the winding number of a closed mesh is an integer, and it
changes by one where a segment crosses a triangle: +1 entering through its front (the side
``cross(b - a, c - a)`` points to), -1 leaving through it. Signed counts, not the parity of the
crossings flipping an inside state: where parts of a mesh overlap (two interpenetrating closed
parts given as one mesh: winding number 2 in the overlap), a point one crossing away from the
overlap has winding number 1 and is inside, which a parity flip reads as outside.

* A row is one chain. The winding number at a voxel centre is the previous centre's plus the
  signed crossings of the segment between them, counted against the triangles whose boxes meet
  either voxel (every triangle the segment can cross: it lies in the two voxels). Two
  consecutive unmarked voxels thus have equal winding numbers, and a marked voxel visits the
  triangles once for all of its work: one ``mesh_query_aabb`` over its box, widened to the
  previous voxel's when that one is marked too, counts the segment from the previous centre,
  the segment to the next centre when that voxel is unmarked (its triangles are all here), and
  the samples.
* A sample's winding number is its voxel centre's plus the signed crossings of the segment
  centre->sample, counted against the triangles whose boxes meet the voxel. A voxel is inside
  (unmarked) or a sample is counted (marked) where its winding number exceeds ``params[4]``.
* A chain starts with a query of the winding number (Warp's fast one, rounded to an integer):
  at a row's first voxel, with no query where its centre lies outside the mesh's box
  (winding number 0), and at the voxel after a centre within ``2**-10`` voxel sizes of the
  surface. Float32 rounding could put such a centre on one side of a nearby triangle for one
  count and on the other side for the next, so its voxel falls back to one query per sample
  and the chain restarts. That distance needs no search: any triangle so close meets the
  voxel, so the least exact point-triangle distance over the voxel's triangles (those whose
  box comes that close) decides.
* A chain is checked where it ends (the row's last centre, or the centre before one within the
  guard) against a query there (0 outside the mesh's box: free on a grid with a margin), when it
  has counted a segment since its own query. A closed mesh passes. A row that fails (a mesh with
  holes, whose winding number also changes off the triangles, or a fast winding number more than
  0.5 off) is walked again anchored, as without chains: a query at every marked centre and at
  the first of each run of unmarked voxels, so such errors stay local instead of running on
  along the row. Errors that cancel before a chain's end are not caught: on an open mesh a few
  centres where the winding number is near 0.5 can then differ from the anchored walk.
* Counted exactly once. Each test takes orientation signs of the segment against the edges
  with every edge in a canonical vertex order (lower index first), so the two faces of an edge
  see the same sign and a segment through the edge counts for one of them. A sample's segment
  takes its plane through the voxel centre (``_edge_plane``; ties, of probability zero for
  jittered samples, on one fixed side). The chain's segments run along x and can pass exactly
  through a vertex (the centre of a fan-triangulated cap on the row's line): their sign is the
  edge's orientation around the row's line in the (y, z) projection, exact ties broken as if
  the line were moved by ``(e, e**2)`` (simulation of simplicity), so a line through a vertex,
  too, enters exactly one of the faces around it.

Warp 1.19 exposes the fast winding number only behind a threshold
(``mesh_query_point_sign_winding_number``); its value comes from Warp's native
``wp::mesh_query_winding_number`` (the function that query calls) through ``wp.func_native``.

Open meshes: the winding number varies continuously off the surface, so every unmarked centre
and every sample is queried.
"""

from typing import no_type_check

import jax
import jax.numpy as jnp

from ._grid import mesh_in_call
from ._wrap import CallableFamily, launch_in_chunks
from ._wrap import warp as wp
from .closest import triangle_distance_sq

wp.set_module_options({"enable_backward": False})

__all__ = ["voxel_fractions"]

RADIUS_PAD = wp.constant(1.0 + 2.0**-10)
SURFACE_GUARD = wp.constant(2.0**-10)  # centre-to-surface distance, in voxel sizes, below which samples are queried
MARK_SLACK = wp.constant(2.0**-16)  # widening of the overlap test, in voxel sizes
UNIT_FROM_BITS = wp.constant(2.0**-24)
BATCH = wp.constant(64)  # samples whose crossings are counted in one pass over the voxel's triangles
_MIX_A = wp.constant(wp.uint32(0x7FEB352D))
_MIX_B = wp.constant(wp.uint32(0x846CA68B))


@wp.func
@no_type_check
def _mix(h: wp.uint32):
    # "lowbias32" integer hash (C. Wellons); bit-identical to geomjax._hashing.lowbias32.
    h = h ^ (h >> wp.uint32(16))
    h = h * _MIX_A
    h = h ^ (h >> wp.uint32(15))
    h = h * _MIX_B
    return h ^ (h >> wp.uint32(16))


@wp.func
@no_type_check
def _jitter(seed: wp.uint32, voxel: wp.uint32, sample: wp.uint32, axis: wp.uint32):
    h = _mix(_mix(_mix(seed) + voxel) + wp.uint32(3) * sample + axis)
    return wp.float32(h >> wp.uint32(8)) * UNIT_FROM_BITS


@wp.func
@no_type_check
def _sample_point(lower: wp.vec3, size: float, strata: int, seed: wp.uint32, voxel: wp.uint32, sample: int):
    """Sample ``s`` lies in sub-cube ``s mod strata**3`` of the voxel, uniformly jittered."""
    cell = sample % (strata * strata * strata)
    s = wp.uint32(sample)
    jitter = wp.vec3(_jitter(seed, voxel, s, wp.uint32(0)), _jitter(seed, voxel, s, wp.uint32(1)), _jitter(seed, voxel, s, wp.uint32(2)))
    sub = wp.vec3(float(cell % strata), float((cell / strata) % strata), float(cell / (strata * strata)))
    return lower + (size / float(strata)) * (sub + jitter)


@wp.func
@no_type_check
def _sample_weight(sample: int, num_samples: int, strata: int):
    """Integer weight of a sample: every sub-cube weighs the same whatever its sample count.

    Sub-cubes hold ``q`` or ``q + 1`` samples; weights ``L / count`` with ``L = q (q + 1)`` (or
    ``q`` when all counts are equal) are integers, so a fraction is one exact integer ratio and
    a voxel with every sample inside gives exactly 1.
    """
    cells = strata * strata * strata
    q = num_samples / cells
    if q * cells == num_samples:
        return 1
    if sample % cells < num_samples - q * cells:
        return q
    return q + 1


@wp.func
@no_type_check
def _weight_total(num_samples: int, strata: int):
    cells = strata * strata * strata
    q = num_samples / cells
    if q * cells == num_samples:
        return num_samples
    return cells * q * (q + 1)


@wp.func
@no_type_check
def _query_inside(mesh: wp.uint64, p: wp.vec3, centre: wp.vec3, reach: float, accuracy: float, threshold: float):
    """``(inside, distance to the surface)``; the radius always reaches the mesh."""
    radius = (wp.length(p - centre) + reach) * RADIUS_PAD
    q = wp.mesh_query_point_sign_winding_number(mesh, p, radius, accuracy, threshold)
    return q.result and q.sign < 0.0, wp.length(wp.mesh_eval_position(mesh, q.face, q.u, q.v) - p)


@wp.func_native("return wp::mesh_query_winding_number(mesh, p, accuracy);")
def _winding_number(mesh: wp.uint64, p: wp.vec3, accuracy: float) -> float:  # type: ignore[empty-body]
    """Fast (Barnes-Hut) generalized winding number: the value that
    ``mesh_query_point_sign_winding_number`` compares with its threshold, which Warp 1.19 does
    not expose as a builtin (mesh built with ``support_winding_number=True``)."""
    ...


@wp.func
@no_type_check
def _start_winding(mesh: wp.uint64, p: wp.vec3, centre: wp.vec3, reach: float, accuracy: float):
    """Winding number where a chain starts: 0 outside the mesh's box (no query), else the fast
    winding number rounded to an integer (meaningful away from the surface: callers check)."""
    if wp.max(wp.abs(p - centre)) > reach:
        return 0
    return int(wp.round(_winding_number(mesh, p, accuracy)))


@wp.func
@no_type_check
def _edge_plane(p: wp.vec3, q: wp.vec3, p_index: int, q_index: int):
    """``(p x q, False)`` or ``(q x p, True)``: the edge's plane through the voxel centre (the
    origin here), from its lower-indexed endpoint, and whether that reverses the edge.

    The two faces sharing an edge thus get bit-identical planes and opposite flags, so a segment
    through the edge is on one side for both (zero counts as one fixed side).
    """
    if p_index < q_index:
        return wp.cross(p, q), False
    return wp.cross(q, p), True


@wp.func
@no_type_check
def _queried_fraction(
    mesh: wp.uint64, lower: wp.vec3, size: float, voxel: wp.uint32, seed: wp.uint32, num_samples: int, strata: int,
    centre: wp.vec3, reach: float, accuracy: float, threshold: float,
):  # fmt: skip
    total = int(0)
    for s in range(num_samples):
        inside, _distance = _query_inside(mesh, _sample_point(lower, size, strata, seed, voxel, s), centre, reach, accuracy, threshold)
        if inside:
            total += _sample_weight(s, num_samples, strata)
    return float(total) / float(_weight_total(num_samples, strata))


@wp.func
@no_type_check
def _row_side(plane: wp.vec3, flip: bool, p: wp.vec3, q: wp.vec3):
    """:func:`_edge_plane`'s side for a segment along x from the voxel centre: the orientation
    of the row's line around the edge in the (y, z) projection (``plane[0]``, the same for
    either direction along x up to a sign that all three edges share), exact zeros broken as
    if the line were moved by ``(e, e**2)``: by ``p_z - q_z``, then ``q_y - p_y`` (canonical
    order), so a line through a vertex is inside exactly one of the projected faces around it.
    """
    first_y = wp.where(flip, q[1], p[1])
    first_z = wp.where(flip, q[2], p[2])
    second_y = wp.where(flip, p[1], q[1])
    second_z = wp.where(flip, p[2], q[2])
    orientation = plane[0]
    if orientation == 0.0:
        orientation = first_z - second_z
    if orientation == 0.0:
        orientation = second_y - first_y
    return (orientation > 0.0) != flip


@wp.func
@no_type_check
def _crossing_fraction(
    mesh: wp.uint64, vertices: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.int32), lower: wp.vec3, size: float,
    voxel: wp.uint32, seed: wp.uint32, num_samples: int, strata: int, mid: wp.vec3, threshold: float, winding: int,
    back: float, back_reach: float, forward: float,
):  # fmt: skip
    """``(fraction, near, winding number at the next centre)`` of a marked voxel, in one pass
    over its triangles per batch of samples.

    ``winding`` is the winding number at ``mid + (back, 0, 0)`` (the previous centre, or ``mid``
    itself with ``back = 0`` where a chain starts); ``back_reach`` widens the box towards
    the previous voxel (its size where that one is marked, else 0: an unmarked voxel meets no
    triangle); ``forward`` is the offset to the next centre where that voxel is unmarked, else 0
    (a zero-length segment crosses nothing). ``near``: the centre is within ``SURFACE_GUARD``
    voxel sizes of a triangle, and the other results are meaningless.
    """
    slack = MARK_SLACK * size
    guard = SURFACE_GUARD * size
    box_lower = lower - wp.vec3(slack, slack, slack)
    box_upper = lower + wp.vec3(size + slack, size + slack, size + slack)
    total = int(0)
    near = bool(False)
    mid_winding = winding
    forward_change = int(0)
    for start in range(0, num_samples, BATCH):
        chain = start == 0  # the segments and the distance, once
        count = wp.min(BATCH, num_samples - start)
        # Sample offsets from the centre, computed once per batch rather than once per triangle.
        dx = wp.vector(dtype=wp.float32, length=BATCH)
        dy = wp.vector(dtype=wp.float32, length=BATCH)
        dz = wp.vector(dtype=wp.float32, length=BATCH)
        for r in range(count):
            d = _sample_point(lower, size, strata, seed, voxel, start + r) - mid
            dx[r] = d[0]
            dy[r] = d[1]
            dz[r] = d[2]
        # Winding number change from the centre to each sample: the signed crossings.
        change = wp.vector(dtype=wp.int32, length=BATCH)
        back_change = int(0)
        query_lower = box_lower
        if chain:
            query_lower = wp.vec3(box_lower[0] - back_reach, box_lower[1], box_lower[2])
        query = wp.mesh_query_aabb(mesh, query_lower, box_upper)
        f = int(0)
        while wp.mesh_query_next(query, f):
            ia = indices[3 * f]
            ib = indices[3 * f + 1]
            ic = indices[3 * f + 2]
            a = vertices[ia] - mid
            b = vertices[ib] - mid
            c = vertices[ic] - mid
            normal = wp.cross(b - a, c - a)
            mid_height = -wp.dot(normal, a)
            # Crossing from the back (height < 0) to the front of a face leaves the part behind it.
            step = wp.where(mid_height < 0.0, -1, 1)
            plane_ab, flip_ab = _edge_plane(a, b, ia, ib)
            plane_bc, flip_bc = _edge_plane(b, c, ib, ic)
            plane_ca, flip_ca = _edge_plane(c, a, ic, ia)
            if chain:
                back_height = mid_height + normal[0] * back
                forward_height = mid_height + normal[0] * forward
                if (mid_height < 0.0) != (back_height < 0.0) or (mid_height < 0.0) != (forward_height < 0.0):
                    side_ab = _row_side(plane_ab, flip_ab, a, b)
                    if side_ab == _row_side(plane_bc, flip_bc, b, c) and side_ab == _row_side(plane_ca, flip_ca, c, a):
                        if (mid_height < 0.0) != (back_height < 0.0):
                            back_change += step
                        if (mid_height < 0.0) != (forward_height < 0.0):
                            forward_change += step
                low = wp.min(wp.min(a, b), c)
                high = wp.max(wp.max(a, b), c)
                if wp.max(low) <= guard and wp.min(high) >= -guard:
                    if triangle_distance_sq(wp.vec3(0.0, 0.0, 0.0), a, b, c) < guard * guard:
                        near = True
            # Samples lie in this voxel: triangles meeting only the previous voxel's box are skipped.
            if wp.max(wp.max(vertices[ia][0], vertices[ib][0]), vertices[ic][0]) >= box_lower[0]:
                for r in range(count):
                    d = wp.vec3(dx[r], dy[r], dz[r])
                    height = mid_height + wp.dot(normal, d)
                    if (mid_height < 0.0) != (height < 0.0):
                        side_ab = (wp.dot(d, plane_ab) > 0.0) != flip_ab
                        if side_ab == ((wp.dot(d, plane_bc) > 0.0) != flip_bc) and side_ab == ((wp.dot(d, plane_ca) > 0.0) != flip_ca):
                            change[r] += step
        if near:
            break
        # The segment centre -> previous centre changes the winding number by back_change.
        mid_winding = mid_winding - back_change
        for r in range(count):
            if float(mid_winding + change[r]) > threshold:
                total += _sample_weight(start + r, num_samples, strata)
    return float(total) / float(_weight_total(num_samples, strata)), near, mid_winding + forward_change


@wp.kernel
@no_type_check
def _mark_kernel(
    vertices: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.int32), params: wp.array(dtype=wp.float32), nx: int, ny: int,
    nz: int, offset: int, marked: wp.array(dtype=wp.int32),
):  # fmt: skip
    _b, item = wp.tid()
    f = item + offset
    a = vertices[indices[3 * f]]
    b = vertices[indices[3 * f + 1]]
    c = vertices[indices[3 * f + 2]]
    origin = wp.vec3(params[0], params[1], params[2])
    inv_size = 1.0 / params[3]
    low = (wp.min(wp.min(a, b), c) - origin) * inv_size - wp.vec3(MARK_SLACK, MARK_SLACK, MARK_SLACK)
    high = (wp.max(wp.max(a, b), c) - origin) * inv_size + wp.vec3(MARK_SLACK, MARK_SLACK, MARK_SLACK)
    if not (wp.isfinite(low) and wp.isfinite(high)):
        return
    # Clamp in float before converting: cell coordinates of far-away triangles overflow int32.
    i0 = int(wp.clamp(wp.floor(low[0]), -1.0, float(nx)))
    j0 = int(wp.clamp(wp.floor(low[1]), -1.0, float(ny)))
    k0 = int(wp.clamp(wp.floor(low[2]), -1.0, float(nz)))
    i1 = int(wp.clamp(wp.floor(high[0]), -1.0, float(nx)))
    j1 = int(wp.clamp(wp.floor(high[1]), -1.0, float(ny)))
    k1 = int(wp.clamp(wp.floor(high[2]), -1.0, float(nz)))
    for k in range(wp.max(k0, 0), wp.min(k1, nz - 1) + 1):
        for j in range(wp.max(j0, 0), wp.min(j1, ny - 1) + 1):
            for i in range(wp.max(i0, 0), wp.min(i1, nx - 1) + 1):
                marked[i + nx * (j + ny * k)] = 1


@wp.kernel
@no_type_check
def _row_kernel(
    mesh: wp.uint64, vertices: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.int32), marked: wp.array(dtype=wp.int32),
    params: wp.array(dtype=wp.float32), nx: int, ny: int, num_samples: int, strata: int, seed: wp.uint32, open_mesh: int,
    offset: int, fractions: wp.array(dtype=wp.float32),
):  # fmt: skip
    _b, item = wp.tid()
    row = item + offset
    j = row % ny
    k = row / ny
    origin = wp.vec3(params[0], params[1], params[2])
    size = params[3]
    threshold = params[4]
    accuracy = params[5]
    centre = wp.vec3(params[6], params[7], params[8])
    reach = params[9]
    half = wp.vec3(0.5 * size, 0.5 * size, 0.5 * size)
    if open_mesh != 0:
        for i in range(nx):
            lower = origin + size * wp.vec3(float(i), float(j), float(k))
            voxel = i + nx * row
            if marked[voxel] == 0:
                inside, _distance = _query_inside(mesh, lower + half, centre, reach, accuracy, threshold)
                fractions[voxel] = wp.where(inside, 1.0, 0.0)
            else:
                fractions[voxel] = _queried_fraction(mesh, lower, size, wp.uint32(voxel), seed, num_samples, strata, centre, reach, accuracy, threshold)
        return
    # Closed meshes: the winding number is carried along the row (module docstring); a row
    # whose chain disagrees with a query where it ends is walked again, anchored: a query at
    # every marked centre and after every marked voxel.
    for attempt in range(2):
        anchored = attempt == 1
        consistent = bool(True)
        # `winding`, where `chained`: the previous centre's winding number, already carried to
        # this centre where this voxel is unmarked; `linked`: counted over a triangle since the
        # chain's query.
        chained = bool(False)
        linked = bool(False)
        previous_marked = bool(False)
        winding = int(0)
        for i in range(nx):
            lower = origin + size * wp.vec3(float(i), float(j), float(k))
            voxel = i + nx * row
            mid = lower + half
            if marked[voxel] == 0:
                # No triangle between this centre and the previous one when that voxel is
                # unmarked too; a marked previous voxel counted the crossings on the way here.
                if not chained:
                    winding = _start_winding(mesh, mid, centre, reach, accuracy)
                    linked = False
                fractions[voxel] = wp.where(float(winding) > threshold, 1.0, 0.0)
                chained = True
                previous_marked = False
                continue
            back = float(0.0)
            back_reach = float(0.0)
            if chained and not anchored:
                back = (origin[0] + size * float(i - 1) + half[0]) - mid[0]
                back_reach = wp.where(previous_marked, size, 0.0)
            else:
                winding = _start_winding(mesh, mid, centre, reach, accuracy)
                linked = False
            forward = float(0.0)
            if i + 1 < nx and not anchored:
                if marked[voxel + 1] == 0:
                    forward = (origin[0] + size * float(i + 1) + half[0]) - mid[0]
            fraction, near, next_winding = _crossing_fraction(
                mesh, vertices, indices, lower, size, wp.uint32(voxel), seed, num_samples, strata, mid, threshold, winding, back, back_reach, forward
            )
            if near:
                # The chain ends at the previous centre: check it there.
                if chained and linked:
                    previous_mid = wp.vec3(origin[0] + size * float(i - 1) + half[0], mid[1], mid[2])
                    if _start_winding(mesh, previous_mid, centre, reach, accuracy) != winding:
                        consistent = False
                        break
                fraction = _queried_fraction(mesh, lower, size, wp.uint32(voxel), seed, num_samples, strata, centre, reach, accuracy, threshold)
            fractions[voxel] = fraction
            linked = linked or back != 0.0 or forward != 0.0
            winding = next_winding
            chained = not (near or anchored)
            previous_marked = True
        if consistent and chained and linked and not anchored:
            last_mid = origin + size * wp.vec3(float(nx - 1), float(j), float(k)) + half
            consistent = _start_winding(mesh, last_mid, centre, reach, accuracy) == winding
        if consistent:
            break


def _fraction_types(scalar, open_mesh: bool) -> dict:
    # The BVH is float32 (Warp's meshes are), whatever the working dtype: no per-dtype types.
    return {"vertices": wp.array(dtype=wp.vec3), "indices": wp.array(dtype=wp.int32), "params": wp.array(dtype=wp.float32),
            "nx": int, "ny": int, "nz": int, "num_samples": int, "strata": int, "seed": int, "fractions": wp.array(dtype=wp.float32)}  # fmt: skip


def _fractions(dtype, open_mesh: bool):
    """The body: mark the voxels that triangles' boxes meet, then fill the grid row by row."""

    def fractions_of(vertices, indices, params, nx, ny, nz, num_samples, strata, seed, fractions):
        marked = wp.zeros(nx * ny * nz, dtype=wp.int32, device=fractions.device)
        launch_in_chunks(_mark_kernel, 1, indices.shape[0] // 3, [vertices, indices, params, nx, ny, nz], [marked])
        with mesh_in_call(vertices, indices, winding_number=True) as (mesh, _):
            inputs = [mesh.id, vertices, indices, marked, params, nx, ny, num_samples, strata, wp.uint32(seed % 2**32), int(open_mesh)]
            launch_in_chunks(_row_kernel, 1, ny * nz, inputs, [fractions], min_chunk=1)

    return fractions_of


_fractions_family = CallableFamily(_fractions, _fraction_types, outputs=("fractions",), runs_on_host=True, module=__name__)


def voxel_fractions(
    vertices: jax.Array, indices: jax.Array, params: jax.Array, grid_dims: tuple[int, int, int], num_samples: int, strata: int, seed: int, open_mesh: bool
) -> jax.Array:
    """Fractions ``(nz, ny, nx)`` float32 (see the module docstring for the inputs).

    ``strata`` is the largest integer whose cube is at most ``num_samples``; ``seed`` any
    integer (used modulo ``2**32``).
    """
    nx, ny, nz = grid_dims
    seed = (seed % 2**32 + 2**31) % 2**32 - 2**31  # FFI attributes are int32; the kernel reads it back as uint32
    (fractions,) = _fractions_family(jnp.float32, bool(open_mesh))(
        vertices, indices, params, nx, ny, nz, num_samples, strata, seed, shapes={"fractions": (nx * ny * nz,)}
    )
    return fractions.reshape(nz, ny, nx)

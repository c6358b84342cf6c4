"""Nodal fracture (LDEC §2.2–2.3, DESIGN.md stage 6): the fracture properties of a material, and the kernels of the
run-time split pass (nodal stress, candidates, claims, partition of a node's star, birth of cohesive elements).

The rules of the pass are written in warpdem/stages/fracture.py's module docstring; the node duplication itself
(re-lumped masses, remapped tets, faces and elements) is warpdem.kernels.topology's.
"""

from __future__ import annotations

import warp as wp

from .cohesive import cohesive_force
from .tets import TetMaterial, elastic_node_force
from .topology import face_in_tet, label_star, local_index, star_find, tet_face, triangle_area_vector

wp.set_module_options({"enable_backward": False})

NEVER = wp.constant(3.4e38)
"""Tensile strength of a material that never splits [Pa]."""

NO_NODE = wp.constant(2147483647)
"""Claim of a tet no candidate has claimed."""


@wp.struct
class FractureMaterial:
    """Fracture properties of one material (index = material id).

    Attributes:
        tensile_strength: T_f, the largest principal nodal stress at which a node splits [Pa]; a very large value
            (3.4e38) for a material that never splits.
        fracture_energy: Γ, the energy per unit area of new crack surface (both faces counted in A_f) [J/m²].
        alpha: α of the weakening law (LDEC eq. 6), in [0, 1] [-].
    """

    tensile_strength: float
    fracture_energy: float
    alpha: float


# ----------------------------------------------------------------------------------------------------------------
# Physics.


@wp.func
def largest_principal(s: wp.mat33) -> wp.vec4:
    """σ1 [Pa] and its unit direction p1 of a symmetric stress (tension positive; LDEC eq. 1: σ1 ≥ σ2 ≥ σ3), as
    (σ1, p1x, p1y, p1z). wp.eig3 gives no order and no sign: the largest eigenvalue is picked (the first of equals)
    and p1's largest component (the first of equals) is made positive, so the same stress always gives the same
    p1."""
    q, d = wp.eig3(s)
    i = int(0)
    if d[1] > d[i]:
        i = 1
    if d[2] > d[i]:
        i = 2
    p = wp.normalize(wp.vec3(q[0, i], q[1, i], q[2, i]))
    k = int(0)
    if wp.abs(p[1]) > wp.abs(p[k]):
        k = 1
    if wp.abs(p[2]) > wp.abs(p[k]):
        k = 2
    if p[k] < 0.0:
        p = -p
    return wp.vec4(d[i], p[0], p[1], p[2])


EIG_MARGIN = wp.constant(1.0e-4)
"""Relative margin [-] (of the stress entries' absolute sum) by which a Gershgorin bound must clear a threshold before
nodal_stress_kernel skips eig3: far above float32's eig3 and summation errors (~1e-6)."""


@wp.func
def stress_bound(s: wp.mat33) -> float:
    """Gershgorin's upper bound of a symmetric stress's largest eigenvalue [Pa]: max_i (σ_ii + Σ_{j≠i} |σ_ij|)."""
    return wp.max(
        s[0, 0] + wp.abs(s[0, 1]) + wp.abs(s[0, 2]),
        wp.max(s[1, 1] + wp.abs(s[1, 0]) + wp.abs(s[1, 2]), s[2, 2] + wp.abs(s[2, 0]) + wp.abs(s[2, 1])),
    )


@wp.func
def entry_sum(s: wp.mat33) -> float:
    """Σ_ij |σ_ij| [Pa]: the scale of a stress's rounding errors."""
    total = float(0.0)
    for i in range(3):
        for j in range(3):
            total += wp.abs(s[i, j])
    return total


@wp.func
def centroid_offset(
    tet_nodes: wp.array(dtype=wp.vec4i), node_q: wp.array(dtype=wp.vec3), t: int, x: wp.vec3, p: wp.vec3
) -> float:
    """(centroid of tet t − x)·p [m]: how far the tet lies on the side p points to of the plane through x."""
    n = tet_nodes[t]
    c = 0.25 * (node_q[n[0]] + node_q[n[1]] + node_q[n[2]] + node_q[n[3]])
    return wp.dot(c - x, p)


@wp.func
def star_side(tet_nodes: wp.array(dtype=wp.vec4i), node_q: wp.array(dtype=wp.vec3), t: int, x: wp.vec3, p: wp.vec3):
    """Side of tet t of a node at x cut by the plane through x normal to p: 1 (+, the new daughter B) when the
    tet's centroid lies on the side p points to, else 0 (−, A keeps the node)."""
    if centroid_offset(tet_nodes, node_q, t, x, p) > 0.0:
        return 1
    return 0


@wp.func
def faces_between_sides(
    tet_nodes: wp.array(dtype=wp.vec4i),
    ref_tet_face_nbr: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    start: int,
    count: int,
    v: int,
    star_comp: wp.array(dtype=int),
) -> int:
    """Faces of node v's star (holding v) between a − tet and a + tet in the unsplit adjacency: the faces that
    open, whose area makes A_f."""
    between = int(0)
    for e in range(start, start + count):
        if star_comp[e] != 0:
            continue
        t = star_tets[e]
        k_v = local_index(tet_nodes[t], v)
        for k in range(4):
            if k == k_v:
                continue
            e2 = star_find(star_tets, start, count, ref_tet_face_nbr[4 * t + k])
            if e2 >= 0:
                if star_comp[e2] == 1:
                    between += 1
    return between


@wp.func
def ref_copy(n: wp.vec4i, node_ref_q: wp.array(dtype=wp.vec3), x: wp.vec3) -> int:
    """The node of a tet at reference position x (daughters of a split share their parent's), -1 if none."""
    for i in range(4):
        if wp.length_sq(node_ref_q[n[i]] - x) == 0.0:
            return n[i]
    return -1


@wp.func
def freed_hinge(
    tet_nodes: wp.array(dtype=wp.vec4i),
    node_ref_q: wp.array(dtype=wp.vec3),
    ref_tet_face_nbr: wp.array(dtype=int),
    no_joints: wp.array(dtype=int),
    node_bonded: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    start: int,
    count: int,
    v: int,
    star_comp: wp.array(dtype=int),
) -> int:
    """1 when node v is a freed hinge (warpdem/stages/fracture.py, "Candidates"): its neighbours' cracks cut its star
    into ≥ 2 pieces (components through the faces no neighbour has opened, :func:`label_star`, written to star_comp) and
    every half-open face of the star is traction-free: each of its other nodes that split across it left daughters
    of which at least one holds no intact cohesive or joint element (``node_bonded`` = 0), so no element joins the
    two copies. Else 0."""
    half_open = int(0)
    # Cheap test first (most nodes in tension have no half-open face): the faces' bonds, then the components.
    for e in range(start, start + count):
        t = star_tets[e]
        n = tet_nodes[t]
        for k in range(4):
            if n[k] == v:
                continue
            t2 = ref_tet_face_nbr[4 * t + k]
            if t2 < 0:
                continue
            f = tet_face(n, k)
            n2 = tet_nodes[t2]
            if face_in_tet(n2, f[0], f[1], f[2]) >= 0:
                continue  # the face still holds both tets (the common case, so tested before the star search)
            if star_find(star_tets, start, count, t2) < 0:
                continue  # v itself split across the face
            half_open += 1
            for j in range(3):
                a = f[j]
                if a == v:
                    continue
                b = ref_copy(n2, node_ref_q, node_ref_q[a])
                if b >= 0 and b != a:
                    if node_bonded[a] > 0 and node_bonded[b] > 0:
                        return 0  # an element may still join a's copies across this face: it carries traction
    if half_open == 0:
        return 0
    if label_star(tet_nodes, start, count, star_tets, v, ref_tet_face_nbr, no_joints, star_comp) < 2:
        return 0
    return 1


@wp.func
def partition_star(
    tet_nodes: wp.array(dtype=wp.vec4i),
    node_q: wp.array(dtype=wp.vec3),
    ref_tet_face_nbr: wp.array(dtype=int),
    no_joints: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    start: int,
    count: int,
    v: int,
    p: wp.vec3,
    star_comp: wp.array(dtype=int),
):
    """Sides of node v's star tets (star_comp: 0 −, A keeps v; 1 +, the new daughter B) for a split normal to p,
    face-consistent with the cracks its neighbours have opened (warpdem/stages/fracture.py, "Partition")."""
    x = node_q[v]
    # Components through the faces no neighbour has opened (a half-open face: its ref neighbour no longer holds it).
    components = label_star(tet_nodes, start, count, star_tets, v, ref_tet_face_nbr, no_joints, star_comp)
    if components >= 2:
        # The neighbours' cracks already cut the star: it splits along them. Each component goes to the side of its
        # mean centroid offset along p; the highest (first of equals) is +, the lowest −, so both sides have tets.
        hi = int(0)
        lo = int(0)
        best_hi = float(-NEVER)
        best_lo = float(NEVER)
        for c in range(components):
            s = float(0.0)
            m = float(0.0)
            for e in range(start, start + count):
                if star_comp[e] == c:
                    s += centroid_offset(tet_nodes, node_q, star_tets[e], x, p)
                    m += 1.0
            s = s / m
            if s > best_hi:
                best_hi = s
                hi = c
            if s < best_lo:
                best_lo = s
                lo = c
        for e in range(start, start + count):
            c = star_comp[e]
            side = int(0)
            if c == hi:
                side = 1
            elif c != lo:
                s = float(0.0)
                for e2 in range(start, start + count):
                    if star_comp[e2] == c:
                        s += centroid_offset(tet_nodes, node_q, star_tets[e2], x, p)
                if s > 0.0:
                    side = 1
            star_comp[e] = -1 - side  # negative while the other entries still hold component labels (>= 0)
        for e in range(start, start + count):
            star_comp[e] = -1 - star_comp[e]
    else:
        # One piece: the plane rule, except that a tet behind a half-open face takes the side that face's outward
        # normal n points away from (+ when Σ -area n·p > 0 over its half-open faces), so the crack runs on through
        # the faces its neighbours have half opened.
        for e in range(start, start + count):
            t = star_tets[e]
            n = tet_nodes[t]
            vote = float(0.0)
            for k in range(4):
                if n[k] == v:
                    continue
                t2 = ref_tet_face_nbr[4 * t + k]
                if star_find(star_tets, start, count, t2) < 0:
                    continue
                f = tet_face(n, k)
                if face_in_tet(tet_nodes[t2], f[0], f[1], f[2]) >= 0:
                    continue
                vote -= wp.dot(triangle_area_vector(node_q[f[0]], node_q[f[1]], node_q[f[2]]), p)
            side = star_side(tet_nodes, node_q, t, x, p)
            if vote > 0.0:
                side = 1
            elif vote < 0.0:
                side = 0
            star_comp[e] = side
    if faces_between_sides(tet_nodes, ref_tet_face_nbr, star_tets, start, count, v, star_comp) == 0:
        # No face would open (A_f = 0): the plane rule, which the candidate test has checked opens one.
        for e in range(start, start + count):
            star_comp[e] = star_side(tet_nodes, node_q, star_tets[e], x, p)


@wp.func
def critical_opening(fracture_energy: float, area: float, alpha: float, fc: float) -> float:
    """δ_c = 2 Γ A_f / ((2 - α) f_c) [m] (LDEC eq. 10, from W_c = (1 - α/2) f_c δ_c = Γ A_f, eq. 9)."""
    return 2.0 * fracture_energy * area / ((2.0 - alpha) * fc)


@wp.func
def cohesive_force_at_split(m_a: float, m_b: float, f_a: wp.vec3, f_b: wp.vec3) -> wp.vec3:
    """f_A/B = (m_A F_B - m_B F_A) / (m_A + m_B) [N]: the force B's part exerts on A that keeps both daughters on
    the parent's acceleration (LDEC eq. 4, from eqs. 2 and 3)."""
    return (m_a * f_b - m_b * f_a) / (m_a + m_b)


# ----------------------------------------------------------------------------------------------------------------
# Kernels of the pass.


@wp.kernel
def nodal_stress_kernel(
    # Model:
    node_ref_q: wp.array(dtype=wp.vec3),
    tet_nodes: wp.array(dtype=wp.vec4i),
    tet_volume: wp.array(dtype=float),
    tet_material: wp.array(dtype=int),
    fracture_material_table: wp.array(dtype=FractureMaterial),
    node_may_split: wp.array(dtype=int),
    ref_tet_face_nbr: wp.array(dtype=int),
    # State in:
    node_count: wp.array(dtype=int),
    node_q: wp.array(dtype=wp.vec3),
    tet_stress: wp.array(dtype=wp.mat33),
    # In:
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    no_joints: wp.array(dtype=int),
    node_bonded: wp.array(dtype=int),
    # Out:
    node_sigma1: wp.array(dtype=float),
    node_p1: wp.array(dtype=wp.vec3),
    candidate: wp.array(dtype=int),
    star_comp: wp.array(dtype=int),
):
    v = wp.tid()  # one thread per node slot
    candidate[v] = 0
    if v >= node_count[0]:
        return
    if node_may_split[v] == 0:
        # σ1 and p1 are only read for candidates (0 where a node cannot be one): a node outside the fracture region
        # needs neither.
        node_sigma1[v] = 0.0
        node_p1[v] = wp.vec3(0.0)
        return
    start = star_offset[v]
    count = star_count[v]
    # LDEC eq. 1: the volume-weighted average Cauchy stress of the node's active tets, summed in ascending tet order.
    s = wp.mat33(0.0)
    volume = float(0.0)
    strength = float(NEVER)
    for e in range(start, start + count):
        t = star_tets[e]
        s += tet_volume[t] * tet_stress[t]
        volume += tet_volume[t]
        strength = wp.min(strength, fracture_material_table[tet_material[t]].tensile_strength)
    if volume <= 0.0 or strength >= NEVER:
        node_sigma1[v] = 0.0
        node_p1[v] = wp.vec3(0.0)
        return
    average = s / volume
    # σ1 (wp.eig3, iterative) costs more than the rest of the node's work together, so it is taken only where the node
    # may be a candidate. Gershgorin bounds σ1 from above; the margin covers eig3's float32 error and the bound's own
    # rounding (both ~1e-6 of the entries), so a node skipped here is one eig3 would have put below the same
    # thresholds, and the candidates are the same bits either way.
    bound = stress_bound(average)
    margin = EIG_MARGIN * entry_sum(average)
    if bound + margin < strength:
        # Below T_f only a freed hinge in tension splits: the cut around it is open and traction-free, and the node
        # alone pins its two pieces together (warpdem/stages/fracture.py, "Candidates"). Its star's components make the
        # partition, so there is a face between the sides. The hinge test (no eig3) goes first: few nodes pass it.
        node_sigma1[v] = 0.0
        node_p1[v] = wp.vec3(0.0)
        if bound + margin <= 0.0:
            return
        hinge = freed_hinge(
            tet_nodes, node_ref_q, ref_tet_face_nbr, no_joints, node_bonded, star_tets, start, count, v, star_comp
        )
        if hinge == 0:
            return
        principal = largest_principal(average)
        node_sigma1[v] = principal[0]
        node_p1[v] = wp.vec3(principal[1], principal[2], principal[3])
        if principal[0] > 0.0:
            candidate[v] = 1
        return
    principal = largest_principal(average)
    sigma1 = principal[0]
    p = wp.vec3(principal[1], principal[2], principal[3])
    node_sigma1[v] = sigma1
    node_p1[v] = p
    if sigma1 < strength:
        if sigma1 > 0.0:
            candidate[v] = freed_hinge(
                tet_nodes, node_ref_q, ref_tet_face_nbr, no_joints, node_bonded, star_tets, start, count, v, star_comp
            )
        return
    # A candidate needs tets on both sides of the plane and a face between them that still holds it (a crack of
    # zero area would be born broken).
    x = node_q[v]
    between = int(0)
    for e in range(start, start + count):
        t = star_tets[e]
        if star_side(tet_nodes, node_q, t, x, p) != 0:
            continue
        k_v = local_index(tet_nodes[t], v)
        for k in range(4):
            if k == k_v:
                continue
            t2 = ref_tet_face_nbr[4 * t + k]
            if t2 < 0:
                continue
            if star_find(star_tets, start, count, t2) >= 0:
                if star_side(tet_nodes, node_q, t2, x, p) == 1:
                    between = 1
    candidate[v] = between


@wp.kernel
def tension_bound_kernel(
    # State in:
    tet_count: wp.array(dtype=int),
    tet_active: wp.array(dtype=int),
    tet_stress: wp.array(dtype=wp.mat33),
    cohesive_broken_total: wp.array(dtype=int),
    # In:
    threshold: float,
    # Out:
    reached: wp.array(dtype=int),
):
    t = wp.tid()  # one thread per tet slot: does any tet's stress bound reach the lowest T_f?
    if t == 0 and cohesive_broken_total[0] > 0:
        reached[0] = 1  # a crack has let go somewhere: a freed hinge may split below T_f
    if t >= tet_count[0] or tet_active[t] == 0:
        return
    # A node's σ1 is the largest eigenvalue of an average of its tets' stresses, at most the largest of theirs
    # (λ_max is convex), so no node can reach T_f while no tet's bound (stress_bound) does.
    if stress_bound(tet_stress[t]) >= threshold:
        reached[0] = 1


@wp.kernel
def count_bonds_kernel(
    # State in:
    element_count: wp.array(dtype=int),
    element_a: wp.array(dtype=int),
    element_b: wp.array(dtype=int),
    element_broken: wp.array(dtype=int),
    # Out:
    node_bonded: wp.array(dtype=int),
):
    i = wp.tid()  # one thread per cohesive (or joint) element slot: its intact element counts at both its nodes
    if i >= element_count[0] or element_broken[i] != 0:
        return
    wp.atomic_add(node_bonded, element_a[i], 1)
    wp.atomic_add(node_bonded, element_b[i], 1)


@wp.kernel
def not_candidate_kernel(
    # In:
    candidate: wp.array(dtype=int),
    # Out:
    dead: wp.array(dtype=int),
):
    v = wp.tid()  # one thread per node slot: the removal flag of the candidate compaction
    dead[v] = 1 - candidate[v]


@wp.kernel
def gather_candidates_kernel(
    # In:
    node_count: wp.array(dtype=int),
    candidate: wp.array(dtype=int),
    candidate_slot: wp.array(dtype=int),
    # Out:
    candidates: wp.array(dtype=int),
    pending: wp.array(dtype=int),
):
    v = wp.tid()  # one thread per node slot; candidates listed in node order (slot by exclusive scan)
    if v >= node_count[0] or candidate[v] == 0:
        return
    candidates[candidate_slot[v]] = v
    pending[candidate_slot[v]] = 1


@wp.kernel
def claim_sigma_kernel(
    # In:
    candidate_count: wp.array(dtype=int),
    candidates: wp.array(dtype=int),
    pending: wp.array(dtype=int),
    node_sigma1: wp.array(dtype=float),
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    # Out:
    claim_sigma: wp.array(dtype=float),
):
    i = wp.tid()  # one thread per candidate; first claim: the largest σ1 on each star tet (float max is exact)
    if i >= candidate_count[0] or pending[i] == 0:
        return
    v = candidates[i]
    for e in range(star_offset[v], star_offset[v] + star_count[v]):
        wp.atomic_max(claim_sigma, star_tets[e], node_sigma1[v])


@wp.kernel
def claim_node_kernel(
    # In:
    candidate_count: wp.array(dtype=int),
    candidates: wp.array(dtype=int),
    pending: wp.array(dtype=int),
    node_sigma1: wp.array(dtype=float),
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    claim_sigma: wp.array(dtype=float),
    # Out:
    claim_node: wp.array(dtype=int),
):
    i = wp.tid()  # one thread per candidate; second claim: the lowest node id among those of the largest σ1
    if i >= candidate_count[0] or pending[i] == 0:
        return
    v = candidates[i]
    for e in range(star_offset[v], star_offset[v] + star_count[v]):
        t = star_tets[e]
        if claim_sigma[t] == node_sigma1[v]:
            wp.atomic_min(claim_node, t, v)


@wp.kernel
def resolve_claims_kernel(
    # Model:
    tet_nodes: wp.array(dtype=wp.vec4i),
    ref_tet_face_nbr: wp.array(dtype=int),
    # State in:
    node_q: wp.array(dtype=wp.vec3),
    # In:
    candidate_count: wp.array(dtype=int),
    candidates: wp.array(dtype=int),
    node_p1: wp.array(dtype=wp.vec3),
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    claim_node: wp.array(dtype=int),
    no_joints: wp.array(dtype=int),
    # Out:
    pending: wp.array(dtype=int),
    won: wp.array(dtype=int),
    copies: wp.array(dtype=int),
    star_comp: wp.array(dtype=int),
    pending_count: wp.array(dtype=int),
):
    i = wp.tid()  # one thread per candidate: it splits this round if it won every tet of its star
    won[i] = 0
    if i >= candidate_count[0] or pending[i] == 0:
        return
    v = candidates[i]
    start = star_offset[v]
    count = star_count[v]
    for e in range(start, start + count):
        if claim_node[star_tets[e]] != v:
            wp.atomic_add(pending_count, 0, 1)  # lost a tet: retry next round
            return
    # Won: no other node of this round touches these tets. Partition the star (+ side: daughter B) with the
    # topology of this round's start (this round's splits are applied after every partition is made).
    partition_star(tet_nodes, node_q, ref_tet_face_nbr, no_joints, star_tets, start, count, v, node_p1[v], star_comp)
    copies[v] = 1
    won[i] = 1
    pending[i] = 0


@wp.kernel
def birth_cohesive_kernel(
    # Model:
    node_ref_q: wp.array(dtype=wp.vec3),
    tet_nodes: wp.array(dtype=wp.vec4i),
    tet_inv_ref: wp.array(dtype=wp.mat33),
    tet_volume: wp.array(dtype=float),
    tet_material: wp.array(dtype=int),
    tet_material_table: wp.array(dtype=TetMaterial),
    fracture_material_table: wp.array(dtype=FractureMaterial),
    ref_tet_face_nbr: wp.array(dtype=int),
    # State in:
    node_u: wp.array(dtype=wp.vec3),
    # In:
    candidate_count: wp.array(dtype=int),
    candidates: wp.array(dtype=int),
    won: wp.array(dtype=int),
    won_offset: wp.array(dtype=int),
    node_p1: wp.array(dtype=wp.vec3),
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    star_comp: wp.array(dtype=int),
    first_new: wp.array(dtype=int),
    # State out:
    cohesive_count: wp.array(dtype=int),
    cohesive_a: wp.array(dtype=int),
    cohesive_b: wp.array(dtype=int),
    cohesive_fc: wp.array(dtype=float),
    cohesive_delta_c: wp.array(dtype=float),
    cohesive_alpha: wp.array(dtype=float),
    cohesive_area: wp.array(dtype=float),
    cohesive_dir: wp.array(dtype=wp.vec3),
    cohesive_d_max: wp.array(dtype=float),
    cohesive_f_prev: wp.array(dtype=wp.vec3),
    cohesive_energy_prev: wp.array(dtype=float),
    cohesive_broken: wp.array(dtype=int),
    cohesive_tet_face: wp.array(dtype=int),
    # Out:
    won_area: wp.array(dtype=float),
):
    i = wp.tid()  # one thread per candidate that split this round: the cohesive element between its daughters
    if i >= candidate_count[0]:
        return
    won_area[i] = 0.0
    if won[i] == 0:
        return
    v = candidates[i]
    start = star_offset[v]
    count = star_count[v]
    f_a = wp.vec3(0.0)
    f_b = wp.vec3(0.0)
    m_a = float(0.0)
    m_b = float(0.0)
    area = float(0.0)
    best = float(-1.0)
    rep = int(-1)
    for e in range(start, start + count):
        t = star_tets[e]
        n = tet_nodes[t]
        k_v = local_index(n, v)
        mat = tet_material_table[tet_material[t]]
        force = elastic_node_force(
            node_u[n[0]], node_u[n[1]], node_u[n[2]], node_u[n[3]], tet_inv_ref[t], tet_volume[t], mat, k_v
        )
        quarter = 0.25 * mat.density * tet_volume[t]
        if star_comp[e] == 1:
            f_b += force
            m_b += quarter
            continue
        f_a += force
        m_a += quarter
        # The faces that open: those of this − tet that hold v and face a + tet of the star (counted once, from the
        # − side), a third of each face's reference area being v's share.
        for k in range(4):
            if k == k_v:
                continue
            slot = 4 * t + k
            t2 = ref_tet_face_nbr[slot]
            if t2 < 0:
                continue
            e2 = star_find(star_tets, start, count, t2)
            if e2 < 0:
                continue
            if star_comp[e2] != 1:
                continue
            f = tet_face(n, k)
            a = wp.length(triangle_area_vector(node_ref_q[f[0]], node_ref_q[f[1]], node_ref_q[f[2]]))
            area += a / 3.0
            if a > best:
                best = a
                rep = slot
    slot_c = cohesive_count[0] + won_offset[i]
    if slot_c >= cohesive_a.shape[0]:
        return  # past capacity: nothing is written (the host grows before the pass)
    # A_f counts both faces of the new crack (LDEC §2.3).
    area_f = 2.0 * area
    fm = fracture_material_table[tet_material[rep // 4]]
    f_ab = cohesive_force_at_split(m_a, m_b, f_a, f_b)
    fc = wp.length(f_ab)
    # The element's direction before any opening: that of eq. 4's force, so that both daughters keep the parent's
    # acceleration exactly (eq. 3), lateral components included; it points to B's side (along p1) in tension. Only a
    # force that does not pull across the plane (not a tensile split) falls back to p1.
    direction = node_p1[v]
    if wp.dot(f_ab, direction) > 0.0:
        direction = f_ab / fc
    delta_c = float(0.0)
    if fc > 0.0:
        delta_c = critical_opening(fm.fracture_energy, area_f, fm.alpha, fc)
    cohesive_a[slot_c] = v
    cohesive_b[slot_c] = first_new[v]
    cohesive_fc[slot_c] = fc
    cohesive_delta_c[slot_c] = delta_c
    cohesive_alpha[slot_c] = fm.alpha
    cohesive_area[slot_c] = area_f
    cohesive_dir[slot_c] = direction
    cohesive_d_max[slot_c] = 0.0
    # The books' trapezoid starts from the force the element is born with (eq. 4's, before any opening) and no
    # spring energy (kernels/cohesive.py).
    cohesive_f_prev[slot_c] = cohesive_force(wp.vec3(0.0), 0.0, fc, delta_c, fm.alpha, direction, delta_c)
    cohesive_energy_prev[slot_c] = 0.0
    cohesive_broken[slot_c] = 0
    cohesive_tet_face[slot_c] = rep
    won_area[i] = area_f


PASS_REACHED = wp.constant(0)
PASS_CANDIDATES = wp.constant(1)
PASS_GO = wp.constant(2)
PASS_BEFORE = wp.constant(3)
PASS_AFTER = wp.constant(4)
PASS_ROUNDS = wp.constant(5)
PASS_SLOTS = 6
"""The split pass's status vector (int32), read back once a pass: a tet reached the tension bound, candidates found,
the rounds ran (candidates and room for them), node count before and after, rounds run."""


@wp.kernel
def begin_rounds_kernel(
    # State in:
    node_count: wp.array(dtype=int),
    # Out:
    pass_status: wp.array(dtype=int),
    more: wp.array(dtype=int),
):
    _i = wp.tid()  # one thread: the report of the rounds (nodes before, nodes after, rounds) and their loop condition
    pass_status[PASS_BEFORE] = node_count[0]
    pass_status[PASS_AFTER] = node_count[0]
    pass_status[PASS_ROUNDS] = 0
    more[0] = 1


@wp.kernel
def pass_gate_kernel(
    # State in:
    node_count: wp.array(dtype=int),
    cohesive_count: wp.array(dtype=int),
    # In:
    candidate_count: wp.array(dtype=int),
    node_capacity: int,
    cohesive_capacity: int,
    # Out:
    pass_status: wp.array(dtype=int),
    go: wp.array(dtype=int),
):
    _i = wp.tid()  # one thread: split now only if there are candidates and room for a daughter and an element each
    n = candidate_count[0]
    pass_status[PASS_CANDIDATES] = n
    go[0] = 0
    if n > 0 and node_count[0] + n <= node_capacity and cohesive_count[0] + n <= cohesive_capacity:
        go[0] = 1


@wp.kernel
def finish_pass_kernel(
    # In:
    reached: wp.array(dtype=int),
    go: wp.array(dtype=int),
    # Out:
    pass_status: wp.array(dtype=int),
):
    _i = wp.tid()  # one thread: the pass's two decisions into its status
    pass_status[PASS_REACHED] = reached[0]
    pass_status[PASS_GO] = go[0]


@wp.kernel
def end_round_kernel(
    # State in:
    node_count: wp.array(dtype=int),
    pending_count: wp.array(dtype=int),
    # In:
    max_rounds: int,
    # Out:
    pass_status: wp.array(dtype=int),
    more: wp.array(dtype=int),
):
    _i = wp.tid()  # one thread: count the round; another while candidates wait and rounds are left
    pass_status[PASS_AFTER] = node_count[0]
    pass_status[PASS_ROUNDS] = pass_status[PASS_ROUNDS] + 1
    more[0] = 0
    if pending_count[0] > 0 and pass_status[PASS_ROUNDS] < max_rounds:
        more[0] = 1


@wp.kernel
def book_splits_kernel(
    # In:
    candidate_count: wp.array(dtype=int),
    won: wp.array(dtype=int),
    won_area: wp.array(dtype=float),
    # State out:
    cohesive_count: wp.array(dtype=int),
    node_splits_total: wp.array(dtype=int),
    crack_area_total: wp.array(dtype=wp.float64),
):
    _i = wp.tid()  # one thread: the round's counts and crack area, summed in candidate order (deterministic)
    n = int(0)
    area = wp.float64(0.0)
    for i in range(candidate_count[0]):
        if won[i] != 0:
            n += 1
            area += wp.float64(won_area[i])
    cohesive_count[0] = cohesive_count[0] + n
    node_splits_total[0] = node_splits_total[0] + n
    crack_area_total[0] = crack_area_total[0] + area

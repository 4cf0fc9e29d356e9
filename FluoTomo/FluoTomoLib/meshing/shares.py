"""Analytic shapes on a mesh: each node's share of a target given as a function.

The ground truths that grade the reconstructions (the phantoms' tube and tongue,
the thesis studies' discs and spheres) are analytic shapes; the FEM that
simulates them carries a nodal field.  Sampling the shape's indicator at the
nodes gives a linear interpolant whose integral depends on where the nodes fall:
on 0.8 mm elements a 2.4 mm tube held +2.6 to +13.2 % more dye than itself
(docs/tomography.md, "The truth's dye"), the studies' 2D discs -3.3 to +2.6 % on
their 0.25 mm data mesh.  :func:`analytic_fractions` gives each node its share
of the shape instead, so that the interpolant holds the shape's true volume.
"""

from __future__ import annotations

import numpy as np

#: quadrature points per simplex that the shape's boundary cuts: the integral's
#: sampling error falls as 1/sqrt of the cut elements times this, far below 0.1 %
#: on the phantoms' targets
FRACTION_POINTS = 256

#: the quasi-random points' seed (the shares are reproducible to the last digit)
FRACTION_SEED = 20261129


def simplex_points(n, dim):
    """(n, dim + 1) barycentric coordinates of n points spread evenly over a
    simplex (a scrambled Sobol set, fixed seed, mapped by sorted spacings, which
    is uniform on the simplex)."""
    from scipy.stats import qmc

    u = np.sort(qmc.Sobol(int(dim), scramble=True, seed=FRACTION_SEED).random(int(n)), axis=1)
    return np.diff(np.hstack([np.zeros((len(u), 1)), u, np.ones((len(u), 1))]), axis=1)


def analytic_fractions(mesh, inside, points_per_element=FRACTION_POINTS):
    """Each node's share of an analytic shape, such that the linear field of the
    shares integrates to the shape's true volume (area in 2D).

    Each share is the lumped L2 projection of the shape's indicator chi,
    ``int(phi_i chi) / int(phi_i)``: exact over the elements wholly inside or
    outside, sampled at ``points_per_element`` points over those the boundary
    cuts (the elements with nodes on both sides and one ring around them, since
    a curved wall can cross an element without enclosing a node).  The shape
    functions sum to one, so ``sum_i share_i int(phi_i)`` is the shape's volume
    to the sampling error.  The price is a blur of at most one element across
    the wall, symmetric about it.

    Parameters
    ----------
    mesh : Mesh
        Triangles or tetrahedra (``nodes_mm``, ``elements``, ``measures``).
    inside : callable
        Points (M, dim) [mm] -> (M,) bool, True inside the shape.
    points_per_element : int

    Returns
    -------
    (N,) float in [0, 1]
    """
    nodes, el = mesh.nodes_mm, mesh.elements
    k = el.shape[1]                                      # nodes per simplex
    at_nodes = np.asarray(inside(nodes), bool)
    vol = np.asarray(mesh.measures, float)
    mixed = at_nodes[el].any(axis=1) & ~at_nodes[el].all(axis=1)
    near = np.zeros(len(nodes), bool)
    near[el[mixed].ravel()] = True
    cut = near[el].any(axis=1)
    integral = np.zeros(len(nodes))
    whole = ~cut
    np.add.at(integral, el[whole].ravel(),
              np.repeat(vol[whole] / k * at_nodes[el[whole]].all(axis=1), k))
    bary = simplex_points(points_per_element, k - 1)
    idx = np.flatnonzero(cut)
    for chunk in np.array_split(idx, len(idx) // 20000 + 1):
        corners = nodes[el[chunk]]                                     # (C, k, dim)
        pts = np.einsum("pk,ckd->cpd", bary, corners).reshape(-1, nodes.shape[1])
        chi = np.asarray(inside(pts), float).reshape(len(chunk), -1)   # (C, P)
        share = chi @ bary / len(bary) * vol[chunk, None]              # (C, k)
        np.add.at(integral, el[chunk].ravel(), share.ravel())
    lumped = np.zeros(len(nodes))
    np.add.at(lumped, el.ravel(), np.repeat(vol / k, k))
    return np.clip(integral / np.where(lumped > 0, lumped, 1.0), 0.0, 1.0)

"""Compiled (numba) FEM assembly straight into the upper triangle in CSR.

PARDISO's Cholesky takes the upper triangle of the symmetric system matrix.
Going through scipy (COO of 16 entries per tetrahedron, COO -> CSR, CSC for
SuperLU, then ``triu``) moved ~5 M entries three times per assembly
(~0.9 s on the 330k-tetrahedron benchmark slab).  Here the sparsity pattern
and, per element, the CSR position of each of its local (i <= j) pairs are
built once per mesh; an assembly is then one pass over the elements adding
10 values each into the CSR data array.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def upper_pattern(el, n, start, n2e):
    """Sparsity of the upper triangle (i <= j) of a P1 matrix on elements ``el``.

    ``start, n2e``: the elements around each node (jacobian_kernels.node_elements).

    Returns
    -------
    indptr (n+1,) int32, indices (nnz,) int32 (sorted within rows),
    pos (M, nl (nl+1)/2) int32: CSR position of element e's local pair
    (a, b), a <= b, in the order (0,0), (0,1), ..., (1,1), (1,2), ...
    diag (n,) int32: position of each diagonal entry.
    """
    M, nl = el.shape
    # row i holds the nodes j >= i that share an element with i
    marker = np.full(n, -1, np.int64)
    indptr = np.zeros(n + 1, np.int32)
    for i in range(n):
        c = 0
        for t in range(start[i], start[i + 1]):
            e = n2e[t]
            for b in range(nl):
                j = el[e, b]
                if j >= i and marker[j] != i:
                    marker[j] = i
                    c += 1
        indptr[i + 1] = indptr[i] + c
    indices = np.empty(indptr[n], np.int32)
    marker[:] = -1
    for i in range(n):
        p = indptr[i]
        for t in range(start[i], start[i + 1]):
            e = n2e[t]
            for b in range(nl):
                j = el[e, b]
                if j >= i and marker[j] != i:
                    marker[j] = i
                    indices[p] = j
                    p += 1
        # insertion sort of the (short) row
        for q in range(indptr[i] + 1, indptr[i + 1]):
            v = indices[q]
            r = q - 1
            while r >= indptr[i] and indices[r] > v:
                indices[r + 1] = indices[r]
                r -= 1
            indices[r + 1] = v
    npair = nl * (nl + 1) // 2
    pos = np.empty((M, npair), np.int32)
    for e in range(M):
        p = 0
        for a in range(nl):
            for b in range(a, nl):
                i, j = el[e, a], el[e, b]
                if j < i:
                    i, j = j, i
                lo, hi = indptr[i], indptr[i + 1] - 1
                while lo < hi:                   # binary search in the sorted row
                    mid = (lo + hi) // 2
                    if indices[mid] < j:
                        lo = mid + 1
                    else:
                        hi = mid
                pos[e, p] = lo
                p += 1
    diag = indptr[:-1].copy()                    # j = i comes first in each row
    return indptr, indices, pos, diag


@njit(cache=True)
def element_gradients(nodes, el):
    """Gradients of the P1 basis functions (M, nl, d) and signed measures (M,).

    Cofactor inverse of x = p0 + J xi per element (d = 2 or 3); the elements
    were checked non-degenerate before.
    """
    M, nl = el.shape
    d = nl - 1
    grad = np.empty((M, nl, d))
    vol = np.empty(M)
    for e in range(M):
        p0 = el[e, 0]
        if d == 3:
            a = nodes[el[e, 1], 0] - nodes[p0, 0]
            b = nodes[el[e, 2], 0] - nodes[p0, 0]
            c = nodes[el[e, 3], 0] - nodes[p0, 0]
            dd = nodes[el[e, 1], 1] - nodes[p0, 1]
            ee = nodes[el[e, 2], 1] - nodes[p0, 1]
            f = nodes[el[e, 3], 1] - nodes[p0, 1]
            g = nodes[el[e, 1], 2] - nodes[p0, 2]
            h = nodes[el[e, 2], 2] - nodes[p0, 2]
            i = nodes[el[e, 3], 2] - nodes[p0, 2]
            # J = [[a, b, c], [dd, ee, f], [g, h, i]] (columns: edges from node 0)
            A, B, C = ee * i - f * h, f * g - dd * i, dd * h - ee * g
            det = a * A + b * B + c * C
            r = 1.0 / det
            # J^-1 = adj(J) / det; its rows are the gradients of xi_1..xi_3
            grad[e, 1, 0] = A * r
            grad[e, 1, 1] = (c * h - b * i) * r
            grad[e, 1, 2] = (b * f - c * ee) * r
            grad[e, 2, 0] = B * r
            grad[e, 2, 1] = (a * i - c * g) * r
            grad[e, 2, 2] = (c * dd - a * f) * r
            grad[e, 3, 0] = C * r
            grad[e, 3, 1] = (b * g - a * h) * r
            grad[e, 3, 2] = (a * ee - b * dd) * r
            vol[e] = det / 6.0
        else:
            a = nodes[el[e, 1], 0] - nodes[p0, 0]
            b = nodes[el[e, 2], 0] - nodes[p0, 0]
            c = nodes[el[e, 1], 1] - nodes[p0, 1]
            dd = nodes[el[e, 2], 1] - nodes[p0, 1]
            det = a * dd - b * c
            r = 1.0 / det
            grad[e, 1, 0], grad[e, 1, 1] = dd * r, -b * r
            grad[e, 2, 0], grad[e, 2, 1] = -c * r, a * r
            vol[e] = det / 2.0
        for x in range(d):
            s = 0.0
            for k in range(1, nl):
                s += grad[e, k, x]
            grad[e, 0, x] = -s
    return grad, vol


@njit(cache=True)
def upper_values(el, pos, grad, vol, c3, D, w, nnz):
    """CSR data of the upper triangle of K(D) + M(w).

    K: stiffness with the element-mean of the nodal D, ``|e| D_e grad_a . grad_b``;
    M: mass weighted by the nodal w, exact P1 triple products
    ``|e| c3 [S (1 + d_ab) + w_a + w_b + 2 d_ab w_a]`` (``|e|``: the element's
    volume; S: sum of w over e).
    """
    M, nl = el.shape
    dim = grad.shape[2]
    data = np.zeros(nnz)
    for e in range(M):
        De = 0.0
        S = 0.0
        for a in range(nl):
            De += D[el[e, a]]
            S += w[el[e, a]]
        De *= vol[e] / nl
        m = vol[e] * c3
        p = 0
        for a in range(nl):
            wa = w[el[e, a]]
            for b in range(a, nl):
                k = 0.0
                for x in range(dim):
                    k += grad[e, a, x] * grad[e, b, x]
                if a == b:
                    v = De * k + m * (2.0 * S + 4.0 * wa)
                else:
                    v = De * k + m * (S + wa + w[el[e, b]])
                data[pos[e, p]] += v
                p += 1
    return data

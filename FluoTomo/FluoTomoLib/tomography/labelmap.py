"""A label map with its geometry, and the frame the tomography works in.

Every computation of the label-map tomography happens in the label map's own
frame ("local"): x_local = D^T (x_RAS - origin), so voxel (i, j, k) sits at
(i s_i, j s_j, k s_k) and the grid is axis-aligned whatever the IJK-to-RAS
direction D (identity, ``diag(-1, -1, 1)`` of a DICOM-derived volume, an
oblique acquisition).  The map is an isometry (a rotation, possibly with a
reflection), and diffusion is isotropic, so meshes, fields and Jacobians
built there are those of the RAS scene.  Points come in and go out in RAS
through :meth:`LabelMap.to_local` and :meth:`LabelMap.to_ras`; volumes go
out on the label map's own grid (same origin, spacing and direction).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fluoguide.errors import FluoInputError

from FluoTomoLib.meshing.voxel import check_direction

#: most labels a label map may have (the prior has one unknown per label)
MAX_LABELS = 64
#: a surface point within this many voxels of a cut side's plane (and facing
#: along its axis) is on the cut face: the iso-surface of a padded mask lies on
#: the plane, and smoothing moves it by a fraction of a voxel
CUT_TOLERANCE_VOXELS = 0.75


#: a label holding more of the tissue's volume than this is a tissue, not an inclusion
INCLUSION_MAX_SHARE = 0.1


@dataclass(eq=False)
class LabelMap:
    """Label map (0 = air / outside) and its RAS geometry.

    Attributes
    ----------
    labels_kji : (K, J, I) int array
    spacing_mm : (3,) voxel size along I, J, K [mm]
    origin_mm : (3,) RAS position of voxel (0, 0, 0) [mm]
    direction : (3, 3) IJK-to-RAS direction cosines (columns = I, J, K)
    source : where it came from (file or node name), for messages
    """

    labels_kji: np.ndarray
    spacing_mm: np.ndarray
    origin_mm: np.ndarray
    direction: np.ndarray = field(default_factory=lambda: np.eye(3))
    source: str | None = None

    def __post_init__(self):
        lab = np.asarray(self.labels_kji)
        where = self.source or "label map"
        if lab.ndim != 3:
            raise FluoInputError("label map must be 3D", file=self.source, field="labels",
                                 value=lab.shape)
        if not (np.issubdtype(lab.dtype, np.integer) or lab.dtype == bool):
            if not np.all(np.isfinite(lab)) or np.any(lab != np.round(lab)):
                raise FluoInputError("labels must be integers", file=self.source,
                                     field="labels", value=str(lab.dtype))
        lab = lab.astype(np.int64)
        if np.any(lab < 0):
            raise FluoInputError("labels must be >= 0 (0 is air)", file=self.source,
                                 field="labels", value=int(lab.min()))
        if not np.any(lab > 0):
            raise FluoInputError("label map has no tissue (every voxel is 0)", file=self.source,
                                 field="labels")
        self.labels_kji = lab
        self.spacing_mm = np.asarray(self.spacing_mm, float).ravel()
        self.origin_mm = np.asarray(self.origin_mm, float).ravel()
        if self.spacing_mm.shape != (3,) or not np.all(np.isfinite(self.spacing_mm)) or \
                np.any(self.spacing_mm <= 0):
            raise FluoInputError("spacing must be three positive numbers (mm)", file=self.source,
                                 field="spacing", value=self.spacing_mm.tolist())
        if self.origin_mm.shape != (3,) or not np.all(np.isfinite(self.origin_mm)):
            raise FluoInputError("origin must be three finite numbers (mm)", file=self.source,
                                 field="origin", value=self.origin_mm.tolist())
        self.direction = check_direction(self.direction, field=f"{where} direction")
        if len(self.labels) > MAX_LABELS:
            raise FluoInputError(f"more than {MAX_LABELS} labels: is this a label map?",
                                 file=self.source, field="labels", value=len(self.labels))

    # ----- construction -----
    @classmethod
    def from_file(cls, path):
        from fluoguide.labelmap_io import read_labelmap

        labels, spacing, origin, direction = read_labelmap(path)
        return cls(labels, spacing, origin, direction, source=str(path))

    @classmethod
    def from_node(cls, node):
        """From a vtkMRMLLabelMapVolumeNode (or any scalar volume of integer labels)."""
        from fluoguide import mrml_io

        if node is None:
            raise FluoInputError("no label map node", field="labelNode")
        geo = mrml_io.volume_geometry(node)
        return cls(mrml_io.volume_array(node).copy(), geo["spacing"], geo["origin"],
                   geo["direction"], source=node.GetName())

    # ----- frames -----
    @property
    def ijk_to_ras(self):
        m = np.eye(4)
        m[:3, :3] = self.direction * self.spacing_mm[None, :]
        m[:3, 3] = self.origin_mm
        return m

    def to_local(self, points_ras):
        """(P, 3) RAS mm -> the label map's frame (voxel ijk at ijk * spacing)."""
        p = np.atleast_2d(np.asarray(points_ras, float))
        return (p - self.origin_mm) @ self.direction

    def to_ras(self, points_local):
        p = np.atleast_2d(np.asarray(points_local, float))
        return self.origin_mm + p @ self.direction.T

    def mesh_to_ras(self, mesh):
        """A mesh of the local frame moved into RAS (elements re-oriented where
        the direction mirrors); ``meta["frame"] = "RAS"``."""
        return self._moved_mesh(mesh, self.to_ras, "RAS")

    def mesh_to_local(self, mesh):
        """A mesh in RAS (e.g. read back from a model node) in the local frame."""
        return self._moved_mesh(mesh, self.to_local, "local")

    def _moved_mesh(self, mesh, move, frame):
        from FluoTomoLib.meshing.mesh import Mesh

        meta = {k: v for k, v in mesh.meta.items() if not str(k).startswith("_")}
        meta["frame"] = frame
        out = Mesh(move(mesh.nodes_mm), mesh.elements, mesh.element_region, mesh.name, meta)
        # a mirroring direction turns every tetrahedron inside out
        return out.oriented() if np.linalg.det(self.direction) < 0 else out

    def vector_to_local(self, vectors_ras):
        return np.atleast_2d(np.asarray(vectors_ras, float)) @ self.direction

    def vector_to_ras(self, vectors_local):
        return np.atleast_2d(np.asarray(vectors_local, float)) @ self.direction.T

    @property
    def local_origin(self):
        """Voxel (0, 0, 0) in the local frame: the origin."""
        return np.zeros(3)

    @property
    def shape_ijk(self):
        return np.array(self.labels_kji.shape[::-1])

    def local_extent(self):
        """(lo, hi) of the voxel boxes in the local frame [mm]."""
        return -0.5 * self.spacing_mm, (self.shape_ijk - 0.5) * self.spacing_mm

    def voxel_centres_local(self):
        """(K*J*I, 3) local coordinates of every voxel centre, in array order."""
        k, j, i = np.indices(self.labels_kji.shape)
        return np.stack([i.ravel(), j.ravel(), k.ravel()], axis=1) * self.spacing_mm

    # ----- regions -----
    @property
    def labels(self):
        """Sorted non-zero labels present."""
        return [int(v) for v in np.unique(self.labels_kji) if v != 0]

    def region_volumes(self):
        """{label: volume mm^3} of every non-zero label."""
        vals, counts = np.unique(self.labels_kji, return_counts=True)
        vox = float(np.prod(self.spacing_mm))
        return {int(v): float(c * vox) for v, c in zip(vals, counts) if v != 0}

    def region_bounds_local(self, label):
        """(lo, hi) local box of one label's voxels [mm]."""
        k, j, i = np.nonzero(self.labels_kji == int(label))
        if len(k) == 0:
            raise FluoInputError("label is not in the label map", file=self.source,
                                 field="label", value=int(label))
        ijk = np.stack([i, j, k], axis=1)
        return ((ijk.min(axis=0) - 0.5) * self.spacing_mm,
                (ijk.max(axis=0) + 0.5) * self.spacing_mm)

    def region_centroid_local(self, label):
        k, j, i = np.nonzero(self.labels_kji == int(label))
        if len(k) == 0:
            raise FluoInputError("label is not in the label map", file=self.source,
                                 field="label", value=int(label))
        return np.array([i.mean(), j.mean(), k.mean()]) * self.spacing_mm

    def default_target(self):
        """The label a reconstruction is graded on when the user names none: the
        smallest region that is not the largest (an inclusion in its tissue);
        None when there is one tissue label."""
        vols = self.region_volumes()
        if len(vols) < 2:
            return None
        largest = max(vols, key=vols.get)
        return min((v for v in vols if v != largest), key=vols.get)

    def inclusion_labels(self, max_share=INCLUSION_MAX_SHARE):
        """The regions a default scan covers when the user names none: every label
        that is not the largest and holds at most ``max_share`` of the tissue's
        volume (inclusions, not tissue layers), smallest first; the default target
        alone when no label is that small; [] with one tissue label."""
        vols = self.region_volumes()
        if len(vols) < 2:
            return []
        largest = max(vols, key=vols.get)
        total = sum(vols.values())
        small = sorted((v for v in vols if v != largest and vols[v] <= max_share * total),
                       key=vols.get)
        return small or [self.default_target()]

    def tissue_bounds_local(self):
        """(lo, hi) local box of every non-zero voxel."""
        k, j, i = np.nonzero(self.labels_kji > 0)
        ijk = np.stack([i, j, k], axis=1)
        return ((ijk.min(axis=0) - 0.5) * self.spacing_mm,
                (ijk.max(axis=0) + 0.5) * self.spacing_mm)

    # ----- cut faces: where the tissue reaches the map's border -----
    def cut_sides(self):
        """The sides of the volume that tissue reaches: [(axis, side)], axis 0..2
        along I, J, K, side 0 (first slice) or 1 (last). A label map's border is
        not skin: tissue there was cropped (a CBCT's field of view, a crop around
        the target) and goes on beyond it."""
        cached = getattr(self, "_cut_sides", None)
        if cached is None:
            tissue = self.labels_kji > 0
            cached = []
            for a in range(3):
                ax = 2 - a                      # (K, J, I) array axis of IJK axis a
                for side, idx in ((0, 0), (1, -1)):
                    if tissue.take(idx, axis=ax).any():
                        cached.append((a, side))
            self._cut_sides = cached
        return list(cached)

    def cut_planes_local(self):
        """[(axis, coordinate mm)] of the cut sides' outer planes in the local frame."""
        lo, hi = self.local_extent()
        return [(a, float(lo[a] if side == 0 else hi[a])) for a, side in self.cut_sides()]

    def on_cut(self, points_local, normals_local=None, tol_voxels=CUT_TOLERANCE_VOXELS):
        """True for points (P, 3) on a cut face: within ``tol_voxels`` voxels of a
        cut side's plane and, with ``normals_local``, facing along its axis (a
        smoothed surface rounds the edge where skin meets the cut)."""
        p = np.atleast_2d(np.asarray(points_local, float))
        out = np.zeros(len(p), bool)
        for a, c in self.cut_planes_local():
            near = np.abs(p[:, a] - c) <= tol_voxels * self.spacing_mm[a]
            if normals_local is not None:
                near &= np.abs(np.atleast_2d(normals_local)[:, a]) > 0.5
            out |= near
        return out

    def cut_facets(self, mesh):
        """Bool mask over a local-frame mesh's boundary facets that lie on a cut
        face of the label map (None when the map has none): the facets where the
        model lets the tissue go on (DiffusionOperator's ``cut_facets``)."""
        if not self.cut_sides():
            return None
        c = mesh.nodes_mm[mesh.boundary_facets].mean(axis=1)
        mask = self.on_cut(c, mesh.boundary_normals)
        return mask if mask.any() else None

    def distance_to_cut(self, points_local):
        """Distance [mm] of each point to the nearest cut face plane (inf without one)."""
        p = np.atleast_2d(np.asarray(points_local, float))
        d = np.full(len(p), np.inf)
        for a, c in self.cut_planes_local():
            d = np.minimum(d, np.abs(p[:, a] - c))
        return d

    # ----- the tissue-air surface -----
    def surface(self):
        """The tissue's surface in the local frame: the 0.5 iso-surface of the
        tissue mask, smoothed without shrinking (FluoNav's surface extraction),
        as ``SurfaceInfo`` (points, triangles, normals, closest-point queries);
        its ``skin`` marks the triangles that are tissue-air, not a cut face."""
        cached = getattr(self, "_surface", None)
        if cached is None:
            cached = SurfaceInfo.from_labelmap(self)
            centres = cached.points[cached.triangles].mean(axis=1)
            cached.skin = ~self.on_cut(centres, cached.normals)
            self._surface = cached
        return cached


class SurfaceInfo:
    """A triangulated tissue surface (local frame) with closest-point and ray
    queries; ``skin`` (per triangle) is False on the cut faces of a label map."""

    def __init__(self, points, triangles, normals, skin=None):
        self.points = np.asarray(points, float)
        self.triangles = np.asarray(triangles, np.int64)
        self.normals = np.asarray(normals, float)     # per triangle, outward
        self.skin = np.ones(len(self.triangles), bool) if skin is None else np.asarray(skin, bool)
        self._locator = None
        self._poly = None
        self._skin_only = None

    @classmethod
    def from_labelmap(cls, lm):
        from vtk.util import numpy_support as ns

        from FluoNavLib.mapping.surface import surface_from_labelmap

        ijk_to_local = np.diag([*lm.spacing_mm, 1.0])
        poly = surface_from_labelmap(lm.labels_kji, ijk_to_local)
        pts = ns.vtk_to_numpy(poly.GetPoints().GetData()).astype(float)
        conn = ns.vtk_to_numpy(poly.GetPolys().GetConnectivityArray()).reshape(-1, 3)
        nrm = ns.vtk_to_numpy(poly.GetCellData().GetNormals()).astype(float)
        out = cls(pts, conn, nrm)
        out._poly = poly
        return out

    def _vtk_locator(self):
        if self._locator is None:
            import vtk

            if self._poly is None:
                from fluoguide.mrml_io import polydata_from_arrays

                self._poly = polydata_from_arrays(self.points, self.triangles)
            loc = vtk.vtkStaticCellLocator()
            loc.SetDataSet(self._poly)
            loc.BuildLocator()
            self._locator = loc
        return self._locator

    def skin_only(self):
        """This surface without its cut faces (itself when it has none)."""
        if self.skin.all():
            return self
        if self._skin_only is None:
            self._skin_only = SurfaceInfo(self.points, self.triangles[self.skin],
                                          self.normals[self.skin])
        return self._skin_only

    def closest_is_skin(self, points):
        """For each point (P, 3): is the closest triangle of the surface skin?"""
        import vtk

        loc = self._vtk_locator()
        pts = np.atleast_2d(np.asarray(points, float))
        out = np.empty(len(pts), bool)
        c = [0.0, 0.0, 0.0]
        cell, sub, d2 = vtk.reference(0), vtk.reference(0), vtk.reference(0.0)
        for n, p in enumerate(pts):
            loc.FindClosestPoint(p.tolist(), c, cell, sub, d2)
            out[n] = self.skin[int(cell)]
        return out

    def closest(self, points):
        """Closest surface point, its triangle's outward normal and the
        distance [mm] for each point (P, 3)."""
        import vtk

        loc = self._vtk_locator()
        pts = np.atleast_2d(np.asarray(points, float))
        out = np.empty_like(pts)
        nrm = np.empty_like(pts)
        dist = np.empty(len(pts))
        c = [0.0, 0.0, 0.0]
        cell = vtk.reference(0)
        sub = vtk.reference(0)
        d2 = vtk.reference(0.0)
        for n, p in enumerate(pts):
            loc.FindClosestPoint(p.tolist(), c, cell, sub, d2)
            out[n] = c
            nrm[n] = self.normals[int(cell)]
            dist[n] = np.sqrt(float(d2))
        return out, nrm, dist

    def cast(self, origins, directions):
        """First hit of rays on the surface: (points, triangle or -1)."""
        from FluoTomoLib.acquisition.noncontact_optodes import ray_triangle_intersect

        pts, _, face = ray_triangle_intersect(origins, directions, self.points, self.triangles)
        return pts, face


#: points farther than this from the tissue surface are refused [mm]
MAX_OFFSET_MM = 2.0


def place_on_surface(lm, points_ras, what, max_offset_mm=MAX_OFFSET_MM, file=None):
    """Move sources or detectors (RAS mm) onto the label map's tissue-air surface.

    The documented rule: each point goes to the closest point of the surface
    (the smoothed 0.5 iso-surface of the tissue mask) and the distance moved is
    reported; a point farther than ``max_offset_mm`` is refused (it is not on
    this tissue: wrong frame, wrong units, LPS instead of RAS...).

    Returns (points in the local frame, distances [mm]).
    """
    local = lm.to_local(points_ras)
    surf = lm.surface()
    q, _, dist = surf.closest(local)
    far = np.flatnonzero(dist > max_offset_mm)
    if len(far):
        i = int(far[0])
        raise FluoInputError(f"{len(far)} point(s) off the tissue surface: this one is "
                             f"{dist[i]:.3g} mm from it (at most {max_offset_mm:g} mm; "
                             "coordinates are RAS mm of the label map's space)", file=file,
                             field=f"{what}[{i}]", value=np.round(points_ras[i], 3).tolist())
    cut = np.flatnonzero(~surf.closest_is_skin(local))
    if len(cut):
        i = int(cut[0])
        raise FluoInputError(f"{len(cut)} point(s) on a cut face of the label map (its border, "
                             "where the tissue was cropped), not on skin: light cannot enter "
                             "or leave there", file=file, field=f"{what}[{i}]",
                             value=np.round(points_ras[i], 3).tolist())
    return q, dist

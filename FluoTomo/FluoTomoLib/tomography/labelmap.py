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

    def tissue_bounds_local(self):
        """(lo, hi) local box of every non-zero voxel."""
        k, j, i = np.nonzero(self.labels_kji > 0)
        ijk = np.stack([i, j, k], axis=1)
        return ((ijk.min(axis=0) - 0.5) * self.spacing_mm,
                (ijk.max(axis=0) + 0.5) * self.spacing_mm)

    # ----- the tissue-air surface -----
    def surface(self):
        """The tissue-air surface in the local frame: the 0.5 iso-surface of the
        tissue mask, smoothed without shrinking (FluoNav's surface extraction),
        as ``SurfaceInfo`` (points, triangles, normals, closest-point queries)."""
        cached = getattr(self, "_surface", None)
        if cached is None:
            cached = SurfaceInfo.from_labelmap(self)
            self._surface = cached
        return cached


class SurfaceInfo:
    """A triangulated tissue-air surface (local frame) with closest-point and
    ray queries."""

    def __init__(self, points, triangles, normals):
        self.points = np.asarray(points, float)
        self.triangles = np.asarray(triangles, np.int64)
        self.normals = np.asarray(normals, float)     # per triangle, outward
        self._locator = None
        self._poly = None

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
    q, _, dist = lm.surface().closest(local)
    far = np.flatnonzero(dist > max_offset_mm)
    if len(far):
        i = int(far[0])
        raise FluoInputError(f"{len(far)} point(s) off the tissue surface: this one is "
                             f"{dist[i]:.3g} mm from it (at most {max_offset_mm:g} mm; "
                             "coordinates are RAS mm of the label map's space)", file=file,
                             field=f"{what}[{i}]", value=np.round(points_ras[i], 3).tolist())
    return q, dist

"""Volume nodes to SimpleITK images and back, geometry exact.

Slicer keeps a volume's geometry as an IJK-to-RAS matrix; SimpleITK as origin, spacing and direction in LPS. Both
index voxels ``(i, j, k)`` = ``(x, y, z)`` and store them x fastest, so the voxel array passes through unchanged and
only the frame flips: ``IJKToRAS = F @ [[D diag(s), o], [0, 1]]`` with ``F = diag(-1, -1, 1, 1)``. Slicer's own
``sitkUtils`` needs the running application's image IO; this works on bare MRML too (slicer-core), which is what
the tests use.
"""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk
import vtk
from vtk.util import numpy_support

LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])
RAS_TO_LPS = LPS_TO_RAS  # the same flip, its own inverse
"""Homogeneous change of frame between LPS and RAS (its own inverse). dpcn_med.geometry holds the same matrix; this
package keeps its own copy because it must import before dpcn_med is installed into Slicer."""

ORTHONORMAL_TOLERANCE = 1e-4


def matrix_to_array(matrix: vtk.vtkMatrix4x4) -> np.ndarray:
    """``(4, 4)`` numpy copy of a VTK matrix."""
    return np.array([[matrix.GetElement(r, c) for c in range(4)] for r in range(4)])


def array_to_matrix(array: np.ndarray) -> vtk.vtkMatrix4x4:
    """VTK matrix from a ``(4, 4)`` array."""
    matrix = vtk.vtkMatrix4x4()
    for r in range(4):
        for c in range(4):
            matrix.SetElement(r, c, float(array[r, c]))
    return matrix


def transform_to_world(transform) -> np.ndarray:
    """``(4, 4)`` RAS matrix of a transform node and all its parents, to world (identity for ``None``).

    Raises:
        ValueError: the chain is not linear (harden or remove the non-linear transform first).
    """
    if transform is None:
        return np.eye(4)
    if not transform.IsTransformToWorldLinear():
        raise ValueError(f"{transform.GetName()}: is not a linear transform (or hangs under one); harden or remove "
                         "it before registering")
    matrix = vtk.vtkMatrix4x4()
    transform.GetMatrixTransformToWorld(matrix)
    return matrix_to_array(matrix)


def parent_to_world(node) -> np.ndarray:
    """``(4, 4)`` RAS matrix taking ``node``'s coordinates to world: its parent transforms, concatenated."""
    return transform_to_world(node.GetParentTransformNode())


def ijk_to_ras(node, *, world: np.ndarray | None = None) -> np.ndarray:
    """``(4, 4)`` IJK-to-RAS matrix of a volume node, with ``world`` (a ``(4, 4)`` RAS matrix) applied on the left."""
    matrix = vtk.vtkMatrix4x4()
    node.GetIJKToRASMatrix(matrix)
    ijk = matrix_to_array(matrix)
    return ijk if world is None else world @ ijk


def volume_to_image(node, *, world: np.ndarray | None = None) -> sitk.Image:
    """A scalar volume node as a SimpleITK image (LPS geometry, the node's voxel type, values copied).

    Args:
        node: ``vtkMRMLScalarVolumeNode`` (or a label map) holding image data.
        world: optional ``(4, 4)`` RAS matrix applied to the geometry, e.g. :func:`parent_to_world` to take the
            volume as shown in the views (its linear parent transforms hardened).

    Raises:
        ValueError: no image data, several components, or a geometry that is not a rotation times spacing (a
            sheared or mirrored-by-transform volume cannot be a SimpleITK image).
    """
    data = node.GetImageData() if node is not None else None
    if data is None or data.GetPointData() is None or data.GetPointData().GetScalars() is None:
        raise ValueError(f"{_name(node)}: holds no image data")
    if data.GetNumberOfScalarComponents() != 1:
        raise ValueError(f"{_name(node)}: has {data.GetNumberOfScalarComponents()} components; pick a scalar volume")
    spacing, direction, origin = _lps_geometry(node, world)
    size = data.GetDimensions()
    array = numpy_support.vtk_to_numpy(data.GetPointData().GetScalars()).reshape(size[::-1])
    image = sitk.GetImageFromArray(array.copy())
    image.SetSpacing(spacing)
    image.SetDirection(direction)
    image.SetOrigin(origin)
    return image


def mask_on_volume(mask, volume, image: sitk.Image, *, volume_world: np.ndarray | None = None,
                   mask_world: np.ndarray | None = None) -> sitk.Image:
    """A label map as a binary mask on a volume's voxels, for ``dpcn-med register --fixed-mask`` / ``--moving-mask``.

    Both nodes are taken as shown (linear parent transforms applied): the mask covers the voxels of ``volume`` that
    it overlays in the views, whatever grid it was drawn on (nearest neighbour).

    Args:
        mask: label map (or scalar) volume node; any non-zero voxel is inside.
        volume: the volume node the mask restricts.
        image: ``volume`` as it is sent to dpcn-med (:func:`volume_to_image`); the mask gets its geometry.
        volume_world, mask_world: ``(4, 4)`` RAS to-world matrices to place the two nodes with, instead of their
            parent transforms (:func:`parent_to_world`): the frame the volume is registered in.

    Returns:
        sitkUInt8 image, 1 inside and 0 outside, on ``image``'s grid.

    Raises:
        ValueError: the mask holds no image data or covers none of the volume's voxels.
    """
    shown = volume_to_image(mask, world=parent_to_world(mask) if mask_world is None else mask_world)
    grid = sitk.Image(image.GetSize(), sitk.sitkUInt8)
    spacing, direction, origin = _lps_geometry(volume, parent_to_world(volume) if volume_world is None else
                                               volume_world)
    grid.SetSpacing(spacing)
    grid.SetDirection(direction)
    grid.SetOrigin(origin)
    inside = sitk.Resample(sitk.Cast(shown != 0, sitk.sitkUInt8), grid, sitk.Transform(), sitk.sitkNearestNeighbor, 0)
    if not sitk.GetArrayViewFromImage(inside).any():
        raise ValueError(f"{_name(mask)}: the mask covers no voxel of {_name(volume)}; choose the mask drawn on it")
    inside.CopyInformation(image)
    return inside


def _lps_geometry(node, world: np.ndarray | None) -> tuple[list[float], list[float], list[float]]:
    """``(spacing, direction, origin)`` of a volume node in LPS, SimpleITK's order, with ``world`` applied.

    Raises:
        ValueError: a zero spacing, or a geometry that is not a rotation times spacing.
    """
    lps = RAS_TO_LPS @ ijk_to_ras(node, world=world)
    columns = lps[:3, :3]
    spacing = np.linalg.norm(columns, axis=0)
    if np.any(spacing <= 0):
        raise ValueError(f"{_name(node)}: has a zero voxel spacing")
    direction = columns / spacing
    if not np.allclose(direction.T @ direction, np.eye(3), atol=ORTHONORMAL_TOLERANCE):
        raise ValueError(f"{_name(node)}: its geometry (with its parent transforms) is sheared or scaled unevenly; "
                         "harden or remove the transform before registering")
    return spacing.tolist(), direction.ravel().tolist(), lps[:3, 3].tolist()


def image_to_volume(image: sitk.Image, node) -> None:
    """Fill a scalar volume node with a SimpleITK image: voxels copied, IJK-to-RAS from the image's LPS geometry.

    Raises:
        ValueError: the image is not 3-D or not scalar.
    """
    if image.GetDimension() != 3 or image.GetNumberOfComponentsPerPixel() != 1:
        raise ValueError(f"{_name(node)}: can only hold a 3-D scalar image, got {image.GetDimension()}-D with "
                         f"{image.GetNumberOfComponentsPerPixel()} components")
    lps = np.eye(4)
    lps[:3, :3] = np.reshape(image.GetDirection(), (3, 3)) * np.asarray(image.GetSpacing())
    lps[:3, 3] = image.GetOrigin()
    array = sitk.GetArrayFromImage(image)
    data = vtk.vtkImageData()
    data.SetDimensions(image.GetSize())
    data.GetPointData().SetScalars(numpy_support.numpy_to_vtk(array.ravel(), deep=True))
    node.SetAndObserveImageData(data)
    node.SetIJKToRASMatrix(array_to_matrix(LPS_TO_RAS @ lps))


def read_volume(scene, path, name: str):
    """A scalar volume node in ``scene`` read from ``path`` by Slicer's own volume storage node, as File > Add Data
    does; for scripts on bare MRML (slicer-core). In the application, ``slicer.util.loadVolume`` does the same.

    Raises:
        ValueError: the storage node could not read the file.
    """
    import slicer  # here, not at the top: the rest of this module needs only VTK

    storage = slicer.vtkMRMLVolumeArchetypeStorageNode()
    scene.AddNode(storage)
    storage.SetFileName(str(path))
    node = slicer.vtkMRMLScalarVolumeNode()
    node.SetName(name)
    scene.AddNode(node)
    if not storage.ReadData(node):
        raise ValueError(f"{path}: Slicer's volume storage node could not read it")
    return node


def _name(node) -> str:
    return node.GetName() if node is not None and node.GetName() else "volume"

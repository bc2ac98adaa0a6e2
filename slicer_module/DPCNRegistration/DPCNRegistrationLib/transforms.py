"""The registration result as a Slicer linear transform node, placed in the moving volume's transform hierarchy.

The transform file dpcn_med writes maps fixed physical points to moving ones (ITK's resampling direction, LPS).
Slicer's transform storage node reads it as the node that moves the moving volume onto the fixed one (to parent,
RAS): ``inv(F T F)``. Reading the file through that storage node, rather than converting the matrix here, keeps the
one convention where Slicer defines it.
"""

from __future__ import annotations

import os

import numpy as np
import slicer
import vtk

from DPCNRegistrationLib.volumes import array_to_matrix, matrix_to_array, transform_to_world

ROLE_ATTRIBUTES = ("DPCNRegistration.FixedVolumeID", "DPCNRegistration.MovingVolumeID")
"""Node attributes naming the volumes a result transform registered (fixed, moving)."""


def read_transform_file(path: str | os.PathLike, scene) -> np.ndarray:
    """``(4, 4)`` to-parent RAS matrix of a linear ITK transform file, as Slicer reads it.

    Raises:
        ValueError: the file is unreadable or not a linear transform.
    """
    storage = slicer.vtkMRMLTransformStorageNode()
    node = slicer.vtkMRMLLinearTransformNode()
    scene.AddNode(storage)
    scene.AddNode(node)
    try:
        storage.SetFileName(os.fspath(path))
        if not storage.ReadData(node) or not node.IsLinear():
            raise ValueError(f"{path}: not a readable linear transform file")
        matrix = vtk.vtkMatrix4x4()
        node.GetMatrixTransformToParent(matrix)
        return matrix_to_array(matrix)
    finally:
        scene.RemoveNode(node)
        scene.RemoveNode(storage)


def base_transform_node(moving, output):
    """The transform node the result goes under: the moving volume's parent, or, when the moving volume already
    hangs under ``output`` (a repeated registration), ``output``'s own parent; ``None`` for world."""
    parent = moving.GetParentTransformNode()
    if output is not None and parent is not None and parent.GetID() == output.GetID():
        return output.GetParentTransformNode()
    return parent


def reusable_output(output, moving, moving_mask=None):
    """``output`` when writing it moves nothing it should not, else ``None`` (a new transform node is made).

    A transform tagged with another moving volume (:data:`ROLE_ATTRIBUTES`) holds that volume's registration; an
    untagged one with nodes under it other than ``moving`` and ``moving_mask`` holds the user's nodes. Writing either
    would move those nodes off where they are. Nodes under a transform tagged with ``moving`` itself were put there to
    follow it (its segmentation, say), and follow it again.
    """
    if output is None:
        return None
    registered = output.GetAttribute(ROLE_ATTRIBUTES[1])
    if registered:
        return output if registered == moving.GetID() else None
    following = {node.GetID() for node in (moving, moving_mask) if node is not None}
    children = moving.GetScene().GetNodesByClass("vtkMRMLTransformableNode")
    for index in range(children.GetNumberOfItems()):
        child = children.GetItemAsObject(index)
        if child.GetTransformNodeID() == output.GetID() and child.GetID() not in following:
            return None
    return output


def place_result(registration: np.ndarray, moving, fixed, output, base) -> None:
    """Set ``output`` so that the moving volume, under it, lands on the fixed one.

    Args:
        registration: ``(4, 4)`` RAS matrix taking the moving volume as it was registered (under ``base``) onto the
            fixed volume in world coordinates.
        moving, fixed: the volume nodes; ``fixed`` and ``moving`` are tagged on ``output`` (:data:`ROLE_ATTRIBUTES`).
        output: ``vtkMRMLLinearTransformNode`` to write; it is put under ``base`` and the moving volume under it.
        base: the transform node the moving volume was registered under (:func:`base_transform_node`), or ``None``.

    Convention:
        The moving volume ends as ``moving -> output -> base -> world``, so world = ``B @ O``, and ``O`` is
        ``inv(B) @ registration @ B`` (``B`` the base's to-world matrix): the base keeps its own meaning and stays
        editable, and the result is a plain linear node a user can invert, harden or save.
    """
    to_world = transform_to_world(base)
    output.SetAndObserveTransformNodeID(base.GetID() if base is not None else None)
    output.SetMatrixTransformToParent(array_to_matrix(np.linalg.inv(to_world) @ registration @ to_world))
    output.SetAttribute(ROLE_ATTRIBUTES[0], fixed.GetID())
    output.SetAttribute(ROLE_ATTRIBUTES[1], moving.GetID())
    moving.SetAndObserveTransformNodeID(output.GetID())

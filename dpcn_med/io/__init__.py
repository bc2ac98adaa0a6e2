"""Every file the project reads or writes: images, masks, transforms, meshes, JSON and text.

Nothing else in ``dpcn_med`` opens a file. Readers check what they read and raise :class:`InputError`
(:class:`InputNotFoundError` for a missing path) with one line, ``"{path}: {problem}; {fix}"``, which the CLI prints
as it is. Writers go through :func:`atomic_output`: a file appears under its final name complete or not at all.

==============  ====================================================================================================
module          contents
==============  ====================================================================================================
``images``      :func:`read_image`, :func:`check_volume`, :func:`read_mask`, :func:`check_mask`,
                :func:`image_summary`, :func:`write_image`
``headers``     an image file read header first: shape, spacing, origin, direction and :func:`check_memory`
``dicom``       a DICOM series read from its folder, its slice positions checked
``integrity``   truncation and corruption forensics (NIfTI, Analyze, MetaImage, gzip); :func:`file_sha256`
``transforms``  :func:`read_transform`, :func:`write_transform`
``atomic``      :func:`atomic_output`, :func:`interrupts_deferred`, the read-back of what ITK's writers wrote
``tables``      :func:`read_text`, :func:`write_text`, :func:`read_json`, :func:`write_json`, :func:`read_csv`,
                :func:`write_csv`
``tensors``     :func:`read_tensors`, :func:`read_tensor_header`, :func:`write_tensors` (``.safetensors``)
``meshes``      :func:`read_mesh`, :func:`is_mesh_path`
==============  ====================================================================================================

The reasons behind the checks, and what was measured: docs/design_notes/io.md.

Convention:
    Physical space is ITK's LPS in millimetres (:mod:`dpcn_med.geometry` owns the frames). Images keep the origin,
    spacing and direction stored in the file; NIfTI stores them as float32, so they round-trip to about 1e-7 there
    and exactly in NRRD and MetaImage.
"""

from dpcn_med.io._common import IMAGE_WRITE_SUFFIXES
from dpcn_med.io.atomic import _umask as _umask  # private, re-exported for tests/train/test_loop.py
from dpcn_med.io.atomic import atomic_output, interrupts_deferred
from dpcn_med.io.headers import GRID_TOLERANCE, MAX_ORIGIN_MM, SPACING_RANGE_MM, WORKING_COPIES, check_memory
from dpcn_med.io.images import check_mask, check_volume, image_summary, read_image, read_mask, write_image
from dpcn_med.io.integrity import file_sha256
from dpcn_med.io.meshes import MESH_SUFFIXES, is_mesh_path, read_mesh
from dpcn_med.io.tables import read_csv, read_json, read_text, write_csv, write_json, write_text
from dpcn_med.io.tensors import PICKLE_SUFFIXES, read_tensor_header, read_tensors, write_tensors
from dpcn_med.io.transforms import TRANSFORM_SUFFIXES, read_transform, write_transform

__all__ = ["GRID_TOLERANCE", "IMAGE_WRITE_SUFFIXES", "MAX_ORIGIN_MM", "MESH_SUFFIXES", "PICKLE_SUFFIXES",
           "SPACING_RANGE_MM", "TRANSFORM_SUFFIXES", "WORKING_COPIES", "atomic_output", "check_mask", "check_memory",
           "check_volume", "file_sha256", "image_summary", "interrupts_deferred", "is_mesh_path", "read_csv",
           "read_image", "read_json", "read_mask", "read_mesh", "read_tensor_header", "read_tensors", "read_text",
           "read_transform", "write_csv", "write_image", "write_json", "write_tensors", "write_text",
           "write_transform"]

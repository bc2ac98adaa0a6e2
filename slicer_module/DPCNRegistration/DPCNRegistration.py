"""DPCN Registration: one-button, initialisation-free CT / MRI / ultrasound registration in 3D Slicer.

A thin shell over dpcn_med: the widget reads the parameter node, the logic writes the two volumes to a temporary
folder, runs ``dpcn-med register`` in a separate process (:mod:`DPCNRegistrationLib`) and loads the transform and the
resampled volume back. No registration maths here.
"""

from __future__ import annotations

import logging
import os
import pathlib
from typing import Annotated

import qt
import slicer
import vtk
from DPCNRegistrationLib import dependencies
from DPCNRegistrationLib.logic import Registration, RegistrationError, Result, register_volumes
from DPCNRegistrationLib.process import Options
from DPCNRegistrationLib.transforms import reusable_output
from slicer import vtkMRMLLabelMapVolumeNode, vtkMRMLLinearTransformNode, vtkMRMLScalarVolumeNode
from slicer.parameterNodeWrapper import Choice, parameterNodeWrapper
from slicer.ScriptedLoadableModule import (
    ScriptedLoadableModule,
    ScriptedLoadableModuleLogic,
    ScriptedLoadableModuleTest,
    ScriptedLoadableModuleWidget,
)
from slicer.util import VTKObservationMixin

POLL_MILLISECONDS = 100


class DPCNRegistration(ScriptedLoadableModule):
    def __init__(self, parent):
        ScriptedLoadableModule.__init__(self, parent)
        self.parent.title = "DPCN Registration"
        self.parent.categories = ["Registration"]
        self.parent.dependencies = []
        self.parent.contributors = ["dpcn_med developers"]
        self.parent.helpText = (
            "Rigid or similarity registration of two volumes (CT, MRI, ultrasound) from any starting pose, by "
            "differentiable phase correlation (DPCN++), optionally refined by mutual information. Pick the fixed and "
            "moving volumes and press Apply: the moving volume is put under a transform node that aligns it. Name an "
            "ultrasound volume's modality 'us' (Options): it is not detected. "
            "See docs/slicer.md in the dpcn_med repository.")
        self.parent.acknowledgementText = (
            "Method: Chen et al., Differentiable Phase Correlation Network for Versatile Pose Registration (DPCN++). "
            "Built on PyTorch, MONAI and SimpleITK.")


@parameterNodeWrapper
class DPCNRegistrationParameterNode:
    """The module's choices, saved with the scene."""

    fixedVolume: vtkMRMLScalarVolumeNode
    movingVolume: vtkMRMLScalarVolumeNode
    fixedMask: vtkMRMLLabelMapVolumeNode
    movingMask: vtkMRMLLabelMapVolumeNode
    mode: Annotated[str, Choice(["rigid", "similarity"])] = "rigid"
    model: Annotated[str, Choice(["default", "learning-free", "file"])] = "default"
    modelFile: pathlib.Path
    fixedModality: Annotated[str, Choice(["auto", "ct", "mr", "us"])] = "auto"
    movingModality: Annotated[str, Choice(["auto", "ct", "mr", "us"])] = "auto"
    refine: bool = True
    device: Annotated[str, Choice(["auto", "cpu", "cuda"])] = "auto"
    outputTransform: vtkMRMLLinearTransformNode
    outputVolume: vtkMRMLScalarVolumeNode


class DPCNRegistrationWidget(ScriptedLoadableModuleWidget, VTKObservationMixin):
    def __init__(self, parent=None) -> None:
        ScriptedLoadableModuleWidget.__init__(self, parent)
        VTKObservationMixin.__init__(self)
        self.logic = None
        self._parameterNode = None
        self._parameterNodeGuiTag = None
        self._registration: Registration | None = None
        self._timer = qt.QTimer()
        self._timer.setInterval(POLL_MILLISECONDS)
        self._timer.connect("timeout()", self._poll)

    def setup(self) -> None:
        ScriptedLoadableModuleWidget.setup(self)
        uiWidget = slicer.util.loadUI(self.resourcePath("UI/DPCNRegistration.ui"))
        self.layout.addWidget(uiWidget)
        self.ui = slicer.util.childWidgetVariables(uiWidget)
        uiWidget.setMRMLScene(slicer.mrmlScene)
        self.logic = DPCNRegistrationLogic()
        self.addObserver(slicer.mrmlScene, slicer.mrmlScene.StartCloseEvent, self.onSceneStartClose)
        self.addObserver(slicer.mrmlScene, slicer.mrmlScene.EndCloseEvent, self.onSceneEndClose)
        self.ui.applyButton.connect("clicked(bool)", self.onApplyButton)
        self.ui.movingVolumeSelector.connect("currentNodeChanged(vtkMRMLNode*)", self.onMovingVolumeChanged)
        self.layout.addStretch(1)
        self.initializeParameterNode()

    def cleanup(self) -> None:
        self._cancel()
        self.removeObservers()

    def enter(self) -> None:
        self.initializeParameterNode()

    def exit(self) -> None:
        if self._parameterNode:
            self._parameterNode.disconnectGui(self._parameterNodeGuiTag)
            self._parameterNodeGuiTag = None
            self.removeObserver(self._parameterNode, vtk.vtkCommand.ModifiedEvent, self._updateButtons)

    def onSceneStartClose(self, caller, event) -> None:
        self._cancel()
        self.setParameterNode(None)

    def onSceneEndClose(self, caller, event) -> None:
        if self.parent.isEntered:
            self.initializeParameterNode()

    def initializeParameterNode(self) -> None:
        self.setParameterNode(self.logic.getParameterNode())
        if not self._parameterNode.fixedVolume:
            self._parameterNode.fixedVolume = slicer.mrmlScene.GetFirstNodeByClass("vtkMRMLScalarVolumeNode")

    def setParameterNode(self, parameterNode: DPCNRegistrationParameterNode | None) -> None:
        if self._parameterNode:
            self._parameterNode.disconnectGui(self._parameterNodeGuiTag)
            self.removeObserver(self._parameterNode, vtk.vtkCommand.ModifiedEvent, self._updateButtons)
        self._parameterNode = parameterNode
        if self._parameterNode:
            self._parameterNodeGuiTag = self._parameterNode.connectGui(self.ui)
            self.addObserver(self._parameterNode, vtk.vtkCommand.ModifiedEvent, self._updateButtons)
        self._updateButtons()

    def _updateButtons(self, caller=None, event=None) -> None:
        node = self._parameterNode
        running = self._registration is not None
        ready = bool(node and node.fixedVolume and node.movingVolume and node.fixedVolume != node.movingVolume)
        self.ui.applyButton.text = "Cancel" if running else "Apply"
        self.ui.applyButton.enabled = running or ready
        self.ui.applyButton.toolTip = ("Stop the registration" if running else
                                       "Register the moving volume onto the fixed one" if ready else
                                       "Choose two different volumes")
        self.ui.modelFilePathLineEdit.enabled = bool(node and node.model == "file")

    def onMovingVolumeChanged(self, moving) -> None:
        """Clear an output transform that holds another volume's registration (or other nodes): the logic would leave
        it alone and make a new one, and the selector should say so."""
        node = self._parameterNode
        if node and node.outputTransform and moving and reusable_output(node.outputTransform, moving,
                                                                          node.movingMask) is None:
            node.outputTransform = None

    def onApplyButton(self) -> None:
        if self._registration is not None:
            self._cancel()
            self._log("Cancelled.")
            return
        node = self._parameterNode
        with slicer.util.tryWithErrorDisplay("DPCN Registration's dependencies could not be installed."):
            if not self.logic.installDependencies(askConfirmation=True):
                return
        with slicer.util.tryWithErrorDisplay("Registration failed to start.", waitCursor=True):
            self.ui.logTextEdit.clear()
            self.ui.confidenceLabel.text = ""
            self.ui.progressBar.value = 0
            self._registration = self.logic.start(node.fixedVolume, node.movingVolume, self.logic.options(node),
                                                  fixedMask=node.fixedMask, movingMask=node.movingMask,
                                                  outputTransform=node.outputTransform,
                                                  outputVolume=node.outputVolume)
            self._log(f"Registering {node.movingVolume.GetName()} onto {node.fixedVolume.GetName()}...")
            self._timer.start()
        self._updateButtons()

    def _poll(self) -> None:
        registration = self._registration
        if registration is None:
            return
        for event in registration.poll():
            if event.kind == "progress":
                self.ui.progressBar.value = int(round(100 * event.fraction))
                self.ui.progressBar.format = f"{event.text} %p%"
            elif event.kind == "log" and event.text.strip():
                self._log(event.text)
        if not registration.finished:
            return
        self._timer.stop()
        self._registration = None
        try:
            result = registration.finish()
        except (RegistrationError, ValueError, OSError) as error:  # dpcn-med's message, or unreadable outputs
            self._log(f"Failed: {error}")
            slicer.util.errorDisplay(f"Registration failed: {error}")
        else:
            self._showResult(result)
        self._updateButtons()

    def _showResult(self, result: Result) -> None:
        self._parameterNode.outputTransform = result.transform
        quality = (f"Success probability {result.success_probability:.0%} (confidence {result.confidence:.3f})"
                   if result.success_probability is not None else f"Confidence {result.confidence:.3f}")
        text = f"{quality}, {result.overlap:.0%} of the fixed volume overlapped ({result.seconds:.1f} s)."
        if result.low_confidence and result.unverified:
            text += " Not verified (ultrasound): check the alignment in the views before using it."
            self.ui.confidenceLabel.setStyleSheet("color: #c0392b")
            slicer.util.warningDisplay(
                "The result is not verified: nothing yet tells a right ultrasound registration from a wrong one, and "
                "from any starting pose but a nearly right one (a tracked probe's) none registers yet. Check the "
                "alignment in the views before using it.", windowTitle="DPCN Registration")
        elif result.low_confidence:
            text += " Likely wrong: check the alignment in the views before using it."
            self.ui.confidenceLabel.setStyleSheet("color: #c0392b")
            mirrored = result.report.get("mirrored") or {}
            advice = ("The moving volume looks mirrored (flipped left to right it registers with success probability "
                      f"{mirrored.get('success_probability', 0):.0%}): check its header's orientation."
                      if mirrored.get("likely") else "Check the alignment before using it, that both volumes show "
                      "the same anatomy, and that neither header is flipped left to right.")
            slicer.util.warningDisplay(f"The registration is likely wrong ({quality.lower()}). {advice}",
                                       windowTitle="DPCN Registration")
        else:
            self.ui.confidenceLabel.setStyleSheet("")
        self.ui.confidenceLabel.text = text
        self._log(f"Done: {result.transform.GetName()} applied to the moving volume. {text}")
        if result.volume is not None:
            slicer.util.setSliceViewerLayers(background=self._parameterNode.fixedVolume, foreground=result.volume,
                                             foregroundOpacity=0.5)

    def _cancel(self) -> None:
        self._timer.stop()
        if self._registration is not None:
            self._registration.cancel()
            self._registration = None
        if hasattr(self, "ui"):
            self.ui.progressBar.value = 0
            self._updateButtons()

    def _log(self, text: str) -> None:
        self.ui.logTextEdit.appendPlainText(text)
        logging.info(text)


class DPCNRegistrationLogic(ScriptedLoadableModuleLogic):
    """Usable without the widget, e.g. in Slicer's Python console::

        logic = slicer.util.getModuleLogic("DPCNRegistration")
        result = logic.run(getNode("MRBrainT1"), getNode("CTBrain"))
        print(result.confidence, result.transform.GetName())

    Masks (label maps; non-zero inside) restrict each volume to what they cover: ``fixedMask=``, ``movingMask=``.
    """

    def getParameterNode(self) -> DPCNRegistrationParameterNode:
        return DPCNRegistrationParameterNode(super().getParameterNode())

    @staticmethod
    def options(node: DPCNRegistrationParameterNode) -> Options:
        """The registration options chosen in a parameter node."""
        model = node.model
        if model == "file":
            if str(node.modelFile) in ("", ".") or not os.path.isfile(node.modelFile):
                raise ValueError(f"Model is 'file' but {str(node.modelFile)!r} is not a file; choose a model file")
            model = os.fspath(node.modelFile)
        return Options(mode=node.mode, model=model, refine=node.refine, device=node.device,
                       fixed_modality=node.fixedModality, moving_modality=node.movingModality)

    def installDependencies(self, askConfirmation: bool = True) -> bool:
        """Install torch (through the PyTorch extension) and dpcn_med into Slicer's Python if they are missing.

        Returns:
            ``False`` when the user declined, ``True`` when everything is there.

        Raises:
            RuntimeError: an installation failed, or what was installed does not import yet (restart Slicer).
        """
        needed = dependencies.missing()
        if not needed:
            return True
        dependencies.check_python()
        source = dependencies.source(__file__)
        if askConfirmation and not slicer.util.confirmOkCancelDisplay(
                f"DPCN Registration needs {' and '.join(needed)} in Slicer's Python. Install now (dpcn_med from "
                f"{source}; this downloads several hundred MB and may take a few minutes)?",
                windowTitle="DPCN Registration"):
            return False
        if "torch" in needed:
            try:
                import PyTorchUtils
            except ImportError as error:
                raise RuntimeError("Install the PyTorch extension (Extensions Manager) and restart Slicer") from error
            PyTorchUtils.PyTorchUtilsLogic().installTorch(askConfirmation=False)  # raises when it fails
        if "dpcn_med" in needed:
            self._installPackage(source)
        dependencies.check_installed()
        return True

    @staticmethod
    def _installPackage(source: str) -> None:
        """dpcn_med alone (from the checkout or the index), then its requirements without what Slicer provides."""
        import importlib
        import importlib.metadata

        slicer.util.pip_install([source, "--no-deps"])
        importlib.invalidate_caches()
        requirements = dependencies.requirements_to_install(importlib.metadata.requires("dpcn_med") or [])
        if not requirements:
            return
        try:
            import slicer.packaging as slicerPackaging  # Slicer 5.12+: also keeps them out of indirect requirements
        except ImportError:
            slicer.util.pip_install(requirements)
            return
        from packaging.requirements import Requirement

        slicerPackaging.pip_ensure([Requirement(r) for r in requirements],
                                   skip_packages=list(dependencies.SLICER_PROVIDED_NAMES), prompt_install=False,
                                   skip_in_testing=False, requester="DPCNRegistration")

    def start(self, fixed, moving, options: Options | None = None, *, fixedMask=None, movingMask=None,
              outputTransform=None, outputVolume=None) -> Registration:
        """Start registering ``moving`` onto ``fixed`` in a separate process; see :class:`Registration`."""
        return Registration(fixed, moving, options, fixed_mask=fixedMask, moving_mask=movingMask,
                            output_transform=outputTransform, output_volume=outputVolume,
                            workspace=slicer.app.temporaryPath)

    def run(self, fixed, moving, options: Options | None = None, *, fixedMask=None, movingMask=None,
            outputTransform=None, outputVolume=None, progress=None) -> Result:
        """Register ``moving`` onto ``fixed`` and wait; dependencies are installed first (with confirmation)."""
        if not self.installDependencies(askConfirmation=True):
            raise RuntimeError("DPCN Registration's dependencies are not installed: installing them was declined")
        return register_volumes(fixed, moving, options, fixed_mask=fixedMask, moving_mask=movingMask,
                                output_transform=outputTransform, output_volume=outputVolume, progress=progress,
                                workspace=slicer.app.temporaryPath)


class DPCNRegistrationTest(ScriptedLoadableModuleTest):
    """Registers SampleData's CTBrain to MRBrainT1 from the stored pose and from a start turned by 90 degrees."""

    def setUp(self) -> None:
        slicer.mrmlScene.Clear()

    def runTest(self) -> None:
        self.setUp()
        self.test_CTBrainToMRBrainT1FromRotatedStart()

    def test_CTBrainToMRBrainT1FromRotatedStart(self) -> None:
        import numpy as np
        import SampleData
        from DPCNRegistrationLib.volumes import ijk_to_ras, transform_to_world

        self.delayDisplay("Loading CTBrain and MRBrainT1")
        nodes = {node.GetName(): node for node in SampleData.downloadSamples("CTMRBrain")}
        fixed, moving = nodes["MRBrainT1"], nodes["CTBrain"]
        logic = DPCNRegistrationLogic()
        self.assertTrue(logic.installDependencies(askConfirmation=False))

        self.delayDisplay("Registering from the stored pose")
        reference = logic.run(fixed, moving)
        self.assertFalse(reference.low_confidence, f"confidence {reference.confidence}")
        self.assertEqual(moving.GetParentTransformNode().GetID(), reference.transform.GetID())
        referenceWorld = transform_to_world(reference.transform)

        self.delayDisplay("Turning CTBrain by 90 degrees about its anterior-posterior axis and registering again")
        moving.SetAndObserveTransformNodeID(None)
        dimensions = np.array(moving.GetImageData().GetDimensions())
        corners = np.array([[i, j, k, 1.0] for i in (0, dimensions[0] - 1) for j in (0, dimensions[1] - 1)
                            for k in (0, dimensions[2] - 1)])
        storedCorners = (ijk_to_ras(moving) @ corners.T).T[:, :3]
        centre = storedCorners.mean(axis=0)
        turn = vtk.vtkTransform()
        turn.Translate(*centre)
        turn.RotateY(90)
        turn.Translate(*(-centre))
        turnNode = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLLinearTransformNode", "turn by 90 degrees")
        turnNode.SetMatrixTransformToParent(turn.GetMatrix())
        moving.SetAndObserveTransformNodeID(turnNode.GetID())
        moving.HardenTransform()
        slicer.mrmlScene.RemoveNode(turnNode)
        output = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLScalarVolumeNode", "CTBrain resampled")
        result = logic.run(fixed, moving, Options(), outputVolume=output)
        self.assertFalse(result.low_confidence, f"confidence {result.confidence}")
        self.assertIsNotNone(output.GetImageData())

        # Both starts must end with the CT's corners in the same place (within 3 mm).
        finalCorners = (transform_to_world(result.transform) @ ijk_to_ras(moving) @ corners.T).T[:, :3]
        expectedCorners = (referenceWorld @ np.vstack([storedCorners.T, np.ones(len(corners))])).T[:, :3]
        error = np.linalg.norm(finalCorners - expectedCorners, axis=1).max()
        self.assertLess(error, 3.0, f"the two starts disagree by {error:.1f} mm at the CT's corners")
        self.delayDisplay(f"Test passed: the starts agree within {error:.2f} mm")

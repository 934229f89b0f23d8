"""Geometry: from keypoints to needle poses, pure NumPy/OpenCV. Imports nothing of the rest of
``common``.

Conventions: 4x4 ``T_a_b`` maps frame b to frame a (``p_a = T_a_b @ p_b``), metres and radians
(degrees only in names ending ``_deg``); OpenCV cameras (x right, y down, z forward). Frames:
``world``, ``ecm``, ``left``, ``right``, ``needle`` (docs/dataset.md).

Modules (``python -m common.layout`` writes this list from their docstrings):

- ``arc_problem``: The dense fit's residuals, precomputed per rig and needle: the projected model
  arc in both cameras, each observed centreline point's foot on it (Newton steps along the exact
  projected circle), the keypoint and curve residuals with their analytic Jacobians over ``[w, v]``
  (a rotation vector left-multiplied in the ECM frame, a translation in the ECM frame), and the
  robust (Cauchy) loss.
- ``arc_support``: How much of a fitted arc the images saw: the share of the needle's arc, at a
  pose, that an observed centreline point or keypoint lies near in a camera.
- ``arm_correction``: An arm's kinematic error, as the tracker estimates it: a lumped correction of
  the reported jaw pose.
- ``camera``: Pinhole cameras and the stereo endoscope rig (OpenCV conventions).
- ``covariance_bound``: The widest a needle pose's covariance may honestly be: no direction of its
  error spread more than knowing nothing of the needle's orientation (``MAX_SIGMA_RAD``) and nothing
  of its position within the working volume (``MAX_SIGMA_M``), 1 sigma.
- ``ecm_kinematics``: Forward kinematics of the da Vinci endoscope arm (ECM), as the dataset spec
  defines it.
- ``end_identity``: Which end of the needle is the tip: combining the cameras' evidence, turning
  observations end for end, and a covariance that spans both answers when the images cannot decide.
- ``error_state``: The error-state pieces of the needle tracker (``common.geometry.needle_tracker``)
  on SE(3): a pose's error ``[w, v]`` (rad, m) with ``R = exp([w]x) R_hat``, ``t = t_hat + v``; the
  motion models' process noise, the jaws' lever arm, the Mahalanobis distance.
- ``fusion``: Multi-view fusion: the needle pose from the last k estimates made while the endoscope
  moves.
- ``lm``: Batched Levenberg-Marquardt over rigid poses: the one loop of the PnP's reprojection fit
  (``reprojection``) and the dense arc fit (``refine``).
- ``needle``: The needle model: a circular arc in the needle frame's x-y plane.
- ``needle_tracker``: The needle tracked over time: at rest, held in an instrument's jaws, or free
  and moving.
- ``observations``: Keypoint observations for the pose solvers, and the error they raise when no
  pose exists.
- ``oracle``: The oracle detector: keypoints from ground truth, with configurable, seeded
  imperfections.
- ``pnp``: Pipeline I: the needle pose ``T_ecm_needle`` from its keypoints by Perspective-n-Point.
- ``refine``: Dense pose refinement: fit the whole projected needle arc in both cameras at once.
- ``refine_tracking``: Frame-to-frame dense refinement: in a video, start each frame from the last
  frame's solutions.
- ``reprojection``: The weighted reprojection error of a needle pose in one or more cameras, its
  analytic Jacobian, its batched Levenberg-Marquardt over many starting poses (``lm``), and the pose
  covariance.
- ``rest_prior``: Prior over the needle's orientation: a needle at rest lies flat on the surface
  beneath it.
- ``stereo_agreement``: Whether a stereo frame's two detections are of one needle, and the track's:
  a detector that tracks a crop from frame to frame (one camera each) can stay locked on a
  distractor (a red marker) for a whole take while the other camera and the track see the needle
  elsewhere.
- ``transforms``: Rigid transforms: 4x4 homogeneous ``T_a_b`` mapping frame b to frame a (metres,
  radians).
- ``triangulation``: Pipeline II: DLT stereo triangulation of the keypoints and Arun's registration
  of the needle model onto them -> ``T_ecm_needle`` (ECM frame, m).
"""

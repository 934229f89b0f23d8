"""Hand labels kept in a dataset folder: each labelled frame's line of frames.jsonl gets the
contract's ground-truth fields (``keypoints``, ``visible``, ``bbox``, ``T_world_needle`` where
the stereo fit gives a sure pose) and needletrack's own ``label`` field (docs/datasets.md: the
clicks, the stated noise, the pose in the ECM frame). frames.jsonl is rewritten whole after
every frame, atomically (a temporary file beside it, then ``os.replace``): a kill loses at most
the frame being edited. Other fields of a line, known or not, are kept as they are.

A frame whose ground truth was not made here (a render's) is never overwritten. The session
(where the user is, the detector's proposals) is kept in ``label-session.json`` in the folder.
"""
from __future__ import annotations

import json
import os
import time
from typing import Optional

import numpy as np

from common.data.dataset import FRAMES_FILE, Dataset, parse_frame
from common.data.writer import TRUTH_FIELDS, write_atomic
from common.frames import CAMERAS
from common.geometry.transforms import inv_T
from common.label.fit import LabelError, LabelFit

SESSION_FILE = "label-session.json"
LABEL_FIELD = "label"
LABELLED_BY = "needletrack label"


def _r(a, nd: int = 4):
    return np.round(np.asarray(a, float), nd).tolist()


class LabelStore:
    """The labels of one folder. ``status(i)``: ``labelled``, ``no_needle``, ``truth`` (ground truth
    not made here: read only) or ``unlabelled``; ``label(i)`` the ``label`` field or None;
    ``save(i, ...)`` writes one frame's label; ``session``/``save_session`` the session state."""

    def __init__(self, folder: str):
        self.ds = Dataset(folder)
        self.path = self.ds.path
        self.frames_path = os.path.join(self.path, FRAMES_FILE)
        with open(self.frames_path, "r", encoding="utf-8-sig") as f:
            self.lines = [json.loads(t) for t in f if t.strip()]
        if len(self.lines) != len(self.ds.frames):
            raise LabelError(f"{self.frames_path}: changed while it was read")
        self._stamp = self._file_stamp()
        self.session_path = os.path.join(self.path, SESSION_FILE)
        self.session = self._read_session()

    def __len__(self) -> int:
        return len(self.lines)

    def _file_stamp(self):
        st = os.stat(self.frames_path)
        return st.st_mtime_ns, st.st_size

    def label(self, i: int) -> Optional[dict]:
        v = self.lines[i].get(LABEL_FIELD)
        return v if isinstance(v, dict) else None

    def status(self, i: int) -> str:
        lab = self.label(i)
        if lab is not None:
            return "no_needle" if lab.get("no_needle") else "labelled"
        return "truth" if any(self.lines[i].get(k) is not None for k in TRUTH_FIELDS if k != LABEL_FIELD) \
            else "unlabelled"

    def T_world_ecm(self, i: int) -> Optional[np.ndarray]:
        """The frame's endoscope pose: its ``T_world_ecm``, else the arm's kinematics of its joints."""
        fr = self.ds.frames[i]
        if fr.T_world_ecm is not None:
            return fr.T_world_ecm
        if fr.ecm_joints is not None and self.ds.arm is not None:
            return self.ds.arm.T_world_ecm(fr.ecm_joints)
        return None

    def save(self, i: int, fit: Optional[LabelFit], clicks: dict, *, click_sigma_px: float,
             start: str = "none", edits: int = 0) -> dict:
        """Write frame ``i``'s label: ``fit`` (None: the frame shows no needle) from ``clicks``
        ({camera: CameraClicks}); ``start`` what the frame started from (``proposal``,
        ``previous``, ``none``), ``edits`` the user's changes to it. Returns the new line.
        LabelError (nothing written) for a frame with ground truth not made here, or a
        frames.jsonl changed on disk since it was read."""
        if not 0 <= i < len(self.lines):
            raise LabelError(f"frame {i}: out of range (the folder has {len(self.lines)} frames)")
        if self.status(i) == "truth":
            raise LabelError(f"frame {i} (frames.jsonl:{self.ds.frames[i].line}) holds ground truth not made by "
                             f"{LABELLED_BY} (a render's?); it is not overwritten: label a copy without it "
                             "(needletrack dataset strip-truth SRC OUT)")
        line = {k: v for k, v in self.lines[i].items() if k not in TRUTH_FIELDS}
        lab = {"by": LABELLED_BY, "stamp": round(time.time(), 3), "no_needle": fit is None,
               "clicks": {c: clicks[c].to_json() for c in CAMERAS if c in clicks},
               "click_sigma_px": float(click_sigma_px), "start": start, "edits": int(edits)}
        if fit is None:
            line["visible"] = {c: [False] * 5 for c in CAMERAS}
            line["bbox"] = {c: None for c in CAMERAS}
        else:
            line["keypoints"] = {c: _r(fit.keypoints[c]) for c in CAMERAS}
            line["visible"] = {c: [bool(b) for b in fit.visible[c]] for c in CAMERAS}
            line["bbox"] = {c: None if fit.bbox[c] is None else _r(fit.bbox[c], 2) for c in CAMERAS}
            T_world_ecm = self.T_world_ecm(i)
            if fit.pose_known and T_world_ecm is not None:
                line["T_world_needle"] = (T_world_ecm @ fit.T_ecm_needle).tolist()
            lab.update({"fit": "stereo" if fit.stereo else fit.cameras[0], "snapped": int(fit.snapped),
                        "keypoint_sigma_px": {c: _r(fit.sigma_px[c], 3) for c in CAMERAS},
                        "T_ecm_needle": fit.T_ecm_needle.tolist(), "covariance": fit.covariance.tolist(),
                        "pose_sigma_mm": round(fit.pose_sigma_mm, 4), "pose_sigma_deg": round(fit.pose_sigma_deg, 4),
                        "ambiguous": bool(fit.ambiguous), "rms_px": round(float(fit.rms_px), 3)})
        line[LABEL_FIELD] = lab
        parse_frame(line, self.ds.frames[i].line)          # never write a line the reader refuses
        if self._file_stamp() != self._stamp:
            raise LabelError(f"{self.frames_path} changed on disk since {LABELLED_BY} read it; nothing written "
                             "(restart the page to read it again)")
        lines = list(self.lines)
        lines[i] = line
        write_atomic(self.frames_path, "".join(json.dumps(x, separators=(",", ":")) + "\n" for x in lines).encode())
        self.lines = lines
        self._stamp = self._file_stamp()
        return line

    def label_pose(self, i: int) -> Optional[np.ndarray]:
        """``T_ecm_needle`` of frame ``i``'s label, or None."""
        lab = self.label(i)
        T = None if lab is None else lab.get("T_ecm_needle")
        return None if T is None else np.asarray(T, float)

    def prior_pose(self, i: int) -> Optional[np.ndarray]:
        """The nearest labelled frame's pose, seen from frame ``i``'s endoscope: through the world
        where both frames know their endoscope pose and the needle rests over their sequence,
        else as it was in that frame's endoscope frame. None without a labelled frame."""
        fr = self.ds.frames[i]
        done = [j for j in range(len(self.lines)) if j != i and self.label_pose(j) is not None]
        if not done:
            return None
        same = [j for j in done if fr.sequence is not None and self.ds.frames[j].sequence == fr.sequence]
        j = min(same or done, key=lambda j: abs(j - i))
        T = self.label_pose(j)
        Ti, Tj = self.T_world_ecm(i), self.T_world_ecm(j)
        if j in same and fr.at_rest and Ti is not None and Tj is not None:
            return inv_T(Ti) @ Tj @ T
        return T

    # ------------------------------------------------------------ the session
    def _read_session(self) -> dict:
        try:
            with open(self.session_path, encoding="utf-8") as f:
                s = json.load(f)
        except FileNotFoundError:
            return {}
        except (OSError, ValueError) as exc:
            raise LabelError(f"{self.session_path}: not a session file ({exc}); move it away to start afresh") from None
        return s if isinstance(s, dict) else {}

    def save_session(self, **fields) -> None:
        self.session.update(fields)
        write_atomic(self.session_path, json.dumps(self.session, separators=(",", ":")).encode())

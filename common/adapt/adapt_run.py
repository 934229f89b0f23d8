"""The shipped pipeline over a folder without ground truth, its outputs kept for ``needletrack adapt``.

``record_pipeline`` runs ``pipeline_graph`` (replay -> a detector per camera -> ecm -> refine, every
input queued as ``needletrack eval`` does, the refinement a single-frame method) with the
``recorder`` node as the sink, which writes each refined pose and each detection as a JSON line.
``common.evaluation.recording.read_recording`` reads that file back per frame. A recording that ends with its ``end`` line is
complete: a rerun keeps it (resumable).
"""
from __future__ import annotations

from pathlib import Path

from common.evaluation.recording import RecordingError, recording_complete
from common.evaluation.replay_progress import wait_with_progress


def record_pipeline(folder, out_file, *, model: str | None = None, support_normal=None,
                    log_file=None, progress: bool = True, timeout: float | None = None) -> Path:
    """Run the pipeline over ``folder`` (a dataset folder, ground truth or not) and write its
    refined poses and detections to ``out_file``; returns it. Skips the run when ``out_file``
    is complete already."""
    from common.data.dataset import Dataset
    from common.evaluation.pipeline_graph import (
        GraphRun,
        GraphRunError,
        pipeline_graph,
        recorder_node,
    )
    out_file = Path(out_file)
    if recording_complete(out_file):
        return out_file
    n = len(Dataset(str(folder)))
    out_file.parent.mkdir(parents=True, exist_ok=True)
    partial = out_file.with_suffix(out_file.suffix + ".part")
    det = {"weights": str(Path(model).resolve())} if model else {}
    doc = pipeline_graph(str(folder), detector="learned", detector_params=det, rate=10.0,
                         methods=["refined"], lossless=True, split_detector=True,
                         refine_tracking=False,
                         refine_params={"support_normal_world": list(support_normal)}
                         if support_normal is not None else None,
                         name="needletrack-adapt")
    doc["nodes"].append(recorder_node(doc, partial, split_detector=True))
    log_path = Path(log_file) if log_file else out_file.with_suffix(".log")
    timeout = timeout or (180 + 2.0 * n)      # generous: the detectors pace the run, not the replay
    with open(log_path, "w") as log:
        try:
            with GraphRun(doc, log) as run:
                run.start()
                wait_with_progress(run, n, timeout, show=progress, until=("recorder",))
        except GraphRunError as exc:
            raise RecordingError(f"{folder}: the pipeline failed: {exc}; see {log_path}") from None
    if not recording_complete(partial):
        raise RecordingError(f"{folder}: the recorder wrote no complete {partial}; see {log_path}")
    partial.replace(out_file)
    return out_file


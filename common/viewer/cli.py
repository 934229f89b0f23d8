"""``needletrack view FILE.rrd [--port 9091] [--grpc-port 9877]``: serve a recording (a live
viewer's ``save``, or ``needletrack eval --rrd``) in Rerun's web viewer on 127.0.0.1 and print
its URL; Ctrl-C stops it. Needs the ``viewer`` extra (``pip install -e '.[viewer]'``).

The recording is read here (``rerun.chunk.RrdReader``) and served from this process's gRPC
server on 127.0.0.1:``--grpc-port`` (idle, it costs nothing; Rerun's own ``rerun --serve-web
FILE.rrd`` kept 0.7 of a core busy here, idle). The web viewer's static files are served by
Rerun's command line (the ``rerun`` binary of the ``rerun-sdk`` wheel, ``--serve-web --bind
127.0.0.1``), which, unlike the SDK's ``serve_web_viewer``, can bind loopback only. It is started
directly (not through ``python -m rerun``, whose binary would outlive a killed wrapper) and dies
with its parent.
"""
from __future__ import annotations

import argparse
import ctypes
import signal
import subprocess
import sys
import time
import urllib.parse
from pathlib import Path


def _pdeathsig():
    """In the child: die with the parent (Linux ``PR_SET_PDEATHSIG``)."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)
    except OSError:
        pass


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def web_url(web_port: int, grpc_url: str) -> str:
    """The web viewer's address that opens ``grpc_url`` (``rerun+http://...``)."""
    return f"http://127.0.0.1:{web_port}/?url=" + urllib.parse.quote(grpc_url, safe="")


def rerun_binary() -> str:
    """The ``rerun`` command line binary shipped in the rerun-sdk wheel."""
    import rerun_cli
    exe = Path(rerun_cli.__file__).parent / "rerun"
    if not exe.is_file():
        raise FileNotFoundError(f"{exe}: the rerun binary is missing from rerun-sdk")
    return str(exe)


def serve_web(web_port: int, source: str, grpc_port: int | None = None) -> subprocess.Popen:
    """Start Rerun's web viewer on 127.0.0.1:``web_port`` showing ``source``: a gRPC URL
    (``rerun+http://127.0.0.1:PORT/proxy``: web server only, idle at no cost) or an .rrd file
    (then also Rerun's gRPC server on ``grpc_port``, which polls the file busily: prefer
    ``serve_recording``). The process dies with its parent."""
    cmd = [rerun_binary(), "--serve-web", "--bind", "127.0.0.1",
           "--web-viewer-port", str(web_port)]
    if grpc_port is not None:
        cmd += ["--port", str(grpc_port)]
    return subprocess.Popen(cmd + [str(source)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            stdin=subprocess.DEVNULL, preexec_fn=_pdeathsig)


def serve_recording(path: Path, grpc_port: int, memory_limit: str = "2GiB"):
    """Serve the .rrd file ``path`` (its first recording, same application and recording id)
    from an in-process gRPC server on 127.0.0.1:``grpc_port``; returns the recording stream."""
    import rerun as rr
    from rerun.chunk import RrdReader

    from common.viewer.rerun_log import blueprint
    reader = RrdReader(path)
    entry = reader.recordings()[0]
    rec = rr.RecordingStream(entry.application_id, recording_id=entry.recording_id, send_properties=False)
    rec.set_sinks(rr.GrpcServerSink(bind_ip="127.0.0.1", port=int(grpc_port), server_memory_limit=memory_limit),
                  default_blueprint=blueprint())
    rec.send_chunks(reader.stream(store=entry))
    rec.flush()
    return rec


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="needletrack view", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("rrd", help="a recording (.rrd)")
    p.add_argument("--port", type=int, default=9091, help="web viewer port (default 9091)")
    p.add_argument("--grpc-port", type=int, default=9877, help="Rerun gRPC port (default 9877)")
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    a = p.parse_args(argv)
    if not Path(a.rrd).is_file():
        print(f"needletrack view: {a.rrd}: no such file", file=sys.stderr)
        return 2
    try:
        import rerun  # noqa: F401
    except ImportError:
        print("needletrack view: needs rerun-sdk: pip install -e '.[viewer]'", file=sys.stderr)
        return 1
    rec = serve_recording(Path(a.rrd), a.grpc_port)
    grpc = f"rerun+http://127.0.0.1:{a.grpc_port}/proxy"
    proc = serve_web(a.port, grpc)
    signal.signal(signal.SIGTERM, _interrupt)     # stop the server too, as Ctrl-C does
    print(f"viewer: {web_url(a.port, grpc)}", flush=True)
    deadline = None if a.duration is None else time.monotonic() + a.duration
    try:
        while proc.poll() is None and (deadline is None or time.monotonic() < deadline):
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        if proc.poll() is None:
            proc.terminate()
            proc.wait(10)
        rec.disconnect()
    return 0 if proc.returncode in (0, -signal.SIGTERM) else 1


if __name__ == "__main__":
    sys.exit(main())

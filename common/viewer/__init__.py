"""The live viewer: its pictures, numbers, page and Rerun logging, recordings, and headless
Chromium for screenshots. Colours: ``common.palette``. The node is ``nodes/viewer.py``. Imports
``geometry``, ``runtime`` and ``data`` (a frame's true poses).

Modules (``python -m common.layout`` writes this list from their docstrings):

- ``browser``: Headless Chromium driven over the DevTools protocol (``Chromium``: navigate,
  evaluate, mouse and keys, screenshots), and a screenshot of a web page: the page is opened, left
  to run for ``wait_s`` seconds of real time (its scripts polling, WebGL drawing), then captured.
- ``cli``: ``needletrack view FILE.rrd [--port 9091] [--grpc-port 9877]``: serve a recording (a live
  viewer's ``save``, or ``needletrack eval --rrd``) in Rerun's web viewer on 127.0.0.1 and print its
  URL; Ctrl-C stops it.
- ``draw``: The viewer's pictures: the paper's Fig.
- ``frame``: One viewer frame, shared by the live node and ``needletrack eval --rrd``: the two Fig.
- ``http_request``: HTTP/1.1 request heads for the loopback pages' server
  (``common/viewer/http_server.py``): the bounds on what a client may send (``HttpLimits``), parsing
  a head (``parse_head``, or ``HttpRefusal`` with the status to answer), the ``Host`` check against
  DNS rebinding (``host_name``, ``HostCheck``: ``localhost``, the bound host, allowed names, address
  literals) and a response's bytes (``http_response``).
- ``http_server``: A small HTTP/1.1 server on asyncio in one thread, for the project's loopback
  pages (the live viewer's, ``common/viewer/page.py``; the labelling page's,
  ``common/label/server.py``): GET and HEAD, and where a page asks for it POST with a JSON body;
  keep-alive; whatever the number of clients, every input is bounded (``HttpLimits``):
- ``page``: The viewer's own web page: the Fig.
- ``recording``: ``needletrack eval --rrd FILE``: an evaluation's frames, poses and errors as a
  Rerun recording, to scrub frame by frame (``needletrack view FILE``).
- ``rerun_log``: What the viewer logs to Rerun (``rerun-sdk``, the ``viewer`` extra): one function
  per thing shown, each taking an explicit ``rerun.RecordingStream``.
- ``shot``: ``needletrack screenshot``: a picture of the viewer's page on a graph that runs, made by
  the graph itself (the README's docs/launch.png).
- ``state``: The viewer's numbers: per method its newest pose, error against the truth, rate and
  latency, and short time series of them for the plots.
"""

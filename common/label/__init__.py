"""Hand labels of a dataset folder's frames in the browser (``needletrack label DIR``,
docs/label.md): the needle fitted through the user's clicks (``fit``), the labels kept in the
folder's frames.jsonl (``store``), the detector's proposals and the order of the frames
(``proposals``), the page and its server (``page``, ``server``), what a fine-tune trains on
(``targets``: targets, negatives, hidden keypoints; the held-out takes). May import ``geometry``, ``data``,
``runtime``, ``detector`` (its backends' public API, the wire's sub-pixel centreline) and
``viewer`` (the HTTP server, the browser harness)."""

"""The live viewer: drawing (``draw``), numbers (``state``), the plain page
(``page``; its HTTP request heads ``http_request``), Rerun logging (``rerun_log``, needs the ``viewer`` extra), a headless-Chromium
screenshot (``browser``), ``needletrack screenshot`` (``shot``) and ``needletrack view`` (``cli``). Colours:
``common.palette``. The node is ``nodes/viewer.py``."""

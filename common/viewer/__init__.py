"""The live viewer: drawing (``draw``), numbers (``state``), the plain page
(``page``; its HTTP request heads ``http_request``), Rerun logging (``rerun_log``, needs the ``viewer`` extra), a headless-Chromium
screenshot (``browser``) and ``needletrack view`` (``cli``). The node is ``nodes/viewer.py``."""

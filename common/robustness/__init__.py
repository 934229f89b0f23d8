"""The graph under hostile and unlucky input: the fuzzers (``needletrack bench fuzz``,
``viewer-http``), the intruder check and the soak (``needletrack bench soak``). May import
``evaluation``, ``bench`` and every package above them.
"""

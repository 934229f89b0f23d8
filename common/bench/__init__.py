"""The ``needletrack bench NAME`` benchmarks: speed and accuracy of each stage and of the whole
graph. May import ``evaluation`` and every package above it.
"""

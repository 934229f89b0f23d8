"""The detector on a user's own footage: ``needletrack detect`` (its detections on a user's
files), ``needletrack adapt`` (fitting without labels) and ``needletrack finetune`` (fitting from
hand labels; docs/adapt.md). May import ``evaluation``, ``bench`` and every package above them.
"""

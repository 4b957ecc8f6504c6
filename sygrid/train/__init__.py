"""Training of the perception models on generated datasets (the ``train`` extra: torch and onnx).

One sub-package per model kind, each with its data pipeline, network, losses, loop, ONNX export and a ``command``
module for ``sygrid train <kind>``: ``sygrid.train.detector`` (YOLOv8-style instance segmentation) and
``sygrid.train.pose`` (GDR-Net-style 6D pose). Nothing is imported here, so that ``import sygrid.train`` and the
command-line parser stay cheap and work without torch; the training modules import torch themselves.
"""

"""YOLOv8-style instance segmentation trained on a generated dataset's ``yolo/`` folder, exported to ONNX in the
ultralytics YOLOv8-seg output layout that ``perception.detector.YoloSegDetector`` runs.

Modules: ``config`` (run and augmentation settings; standard library only), ``data`` (dataset reading),
``augment`` (letterbox, augmentation, targets; numpy + OpenCV), ``model`` (the network), ``boxes`` (anchor / DFL /
IoU maths), ``assigner`` (task-aligned assignment), ``loss``, ``evaluate`` (COCO mAP on the val split), ``export``
(ONNX), ``trainer`` (the loop, EMA, checkpoints) and ``command`` (``sygrid train detector``). torch is imported by
the modules that need it, not here.
"""

"""Training code of the learned segmenter (dataset generation, U-Net, loop, ONNX export, evaluation).

Not on the runtime path: ``import torm`` and ``torm.segmentation.learned`` never import this package
(it needs torch and the simulator). Entry point: ``torm train-segmenter`` (:mod:`.run`).
"""

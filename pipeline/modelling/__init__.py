"""Modelling: the three force-model kinds, their training, checkpoints, inference and ONNX export."""

"""The pipeline's stages: thin command-line entry points that `dvc.yaml` runs, one per stage.

Each reads its params section and its input paths, calls library code and writes its outputs.
Nothing imports a stage module (a test checks it): the code lives in the library packages.
"""

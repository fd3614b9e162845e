"""A trained policy that travels: the pretrained folder (``folder``: its files and checks;
``pretrained``: save and load an actor) and the ``torch.export`` / ONNX program (``program``).

This package imports nothing at its top, so the actor can read folders through
:mod:`l1flow_rl.export.folder` without importing the layer above it that imports the actor."""

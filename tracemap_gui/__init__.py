"""The tracemap desktop application (PySide6): the image editor, the 3D viewer and what they share.

The engine project is the model and knows nothing of Qt; `session.Session` wraps it with change signals and
an undo stack, windows observe the session, tools turn mouse gestures into undoable `commands`, and long
engine calls run in `workers`.
"""

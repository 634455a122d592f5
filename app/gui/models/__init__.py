"""Qt-free state of the GUI: the session, the rig adapter, the identification job, the model check, a ring buffer.

Nothing here imports Qt; panels observe these models and act through them.
"""

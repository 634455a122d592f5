"""Qt-free state of the GUI: the session, the rig adapter, the identification job, a ring buffer.

Nothing here imports Qt; panels observe these models and act through them.
"""

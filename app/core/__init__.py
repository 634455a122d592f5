"""Numbers and physics, free of Qt and serial: experiment I/O, geometry, mesh,
finite elements, images, similarity, identification, effects and diagnosis."""

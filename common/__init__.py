"""What the tracker and the mapper share: geometry, I/O, datasets, evaluation."""

"""The study pipeline: the derived stages of a study folder (calibration, reconstruction,
segmentation, registration, assessment), their file-level jobs, ``cbct batch``, ``cbct demo``
and the console's entry point."""

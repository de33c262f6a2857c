"""2D-3D registration of bones to fluoroscopy frames; bone poses and their file."""

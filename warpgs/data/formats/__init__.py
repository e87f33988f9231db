"""Scene formats: COLMAP, transforms.json, light-field arrays, the built-in synthetic scenes; image files,
resizing, undistortion and train/test splits."""

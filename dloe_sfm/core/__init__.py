"""The DLOE method on arrays: numpy / scipy only, no I/O, no pycolmap / open3d / cv2."""

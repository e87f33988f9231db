"""Structure from motion with pycolmap, initial points for the model, similarity transforms between poses."""

"""Image similarity and error metrics."""

"""Small shared utilities (atomic output, hashing)."""

"""Process plumbing: helper threads, signals and captured native output."""

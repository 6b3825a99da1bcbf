"""Service definitions, grants, matching and assignment, sessions and their log."""

"""Small internals that several packages share and that import nothing else of the library."""

"""What a result says against a known truth (phantoms) and how it was chosen."""

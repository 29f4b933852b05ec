"""Presentation: the paper-style tables, the claims read against the paper, galleries and the HTML report."""

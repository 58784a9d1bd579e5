"""Fitting grammar parameters to data, and measuring how well a fitted grammar matches it."""

"""Reusable widgets: map and heatmap views, the job panel."""

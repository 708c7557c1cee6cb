"""Offline stage: pose set, sensitivities, anchors, drape jobs, shape models, database build."""

"""Mapper service: log-odds occupancy grid from laser scans (DESIGN.md §4 "Mapping")."""

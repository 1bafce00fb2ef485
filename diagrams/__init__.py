"""Scenario files of ms_drake (installed as the data package ms_drake_diagrams)."""

"""Models of ms_drake (installed as the data package ms_drake_models): package.xml, robots,
grippers, environments, objects, weights."""

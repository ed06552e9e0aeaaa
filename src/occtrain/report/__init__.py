"""What is read out of finished run directories as tables and pages: a recipe's comparison
table (``compare``) and the results page of ``occtrain report`` (``results``). Below
``run`` and the dashboard: it reads run directories and imports neither."""

"""ECU tables: export to and import from the files engine-management software reads."""

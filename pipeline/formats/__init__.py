"""File formats: readers, writers, validation, output folders, exports."""

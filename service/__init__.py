"""The HTTP service (FastAPI). Never imports Mitsuba or OpenCV."""

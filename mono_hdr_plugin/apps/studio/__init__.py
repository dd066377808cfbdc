"""Scene studio: built-in Mitsuba 3 HDR scenes and a capture simulator."""

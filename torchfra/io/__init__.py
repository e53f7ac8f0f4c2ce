"""Exchange with other finite element codes (Abaqus/CalculiX input decks and their results)."""

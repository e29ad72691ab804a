"""On-line identification of a rover base dynamics (Sujan 2002, ch. 2 and app. B)."""

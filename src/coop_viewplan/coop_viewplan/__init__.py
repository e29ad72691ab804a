"""Next-best-view and task-directed camera placement (Sujan 2002, ch. 3.2.4, 3.3.1, ch. 4)."""

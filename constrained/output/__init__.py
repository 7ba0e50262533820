"""What a run leaves behind: figures, the animation, the interactive viewer page, and the staging of
a verb's files as one consistent set."""

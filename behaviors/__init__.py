"""Runnable behavior scripts: each defines ``async def main(robot)``; run with ``agentsdk run``."""

"""Lessons: the lesson format, the grader, the sandbox that runs student code, the queue and reports.

A lesson is a folder ``lessons/NN-name/`` holding ``lesson.md`` (what the student reads),
``tasks.toml`` (which steps the student writes, points, checks and limits) and ``starter.py``
(the template the student fills in). See :mod:`lab.lessons.format` for the format,
:mod:`lab.lessons.grader` for grading (``vision-lab grade``), :mod:`lab.lessons.sandbox` for how
student code is contained, :mod:`lab.lessons.store` for the persistent submission queue behind
the REST API, and :mod:`lab.lessons.live` for the viewer's lesson mode.

This package's ``__init__`` imports nothing: the sandboxed child process imports
:mod:`lab.lessons.child` before it locks itself down, and must not pull in the grader.
"""

"""The application layer (no viser): what the app does, testable without a browser.

``context.AppContext`` (one per served session) owns the session, the frame store, the jobs and
the event bus; ``annotate.AnnotateState`` and ``review.ReviewState`` (one per browser) turn every
user action into a session command and return its journal entry; ``events`` is the one place a
journal entry becomes topics. ``app.ui`` draws all of it with viser.
"""

"""The labelling web app (FastAPI): one page that plays a query's two clips side by side
and takes the answer by button or key; a JSON API under /api.

Served by uvicorn on 127.0.0.1 unless told otherwise; on any other address every request
needs the access token (the `token` query parameter or the X-Hprior-Token header).

FastAPI is imported when an app is made, not with this module: a training run that may ask a
person imports the labelling package without paying for the web framework. (No `from
__future__ import annotations` here: FastAPI reads the request bodies' types at run time.)"""
import secrets

from hprior_jax.labelling.clips import clip_path
from hprior_jax.labelling.goals import goal
from hprior_jax.labelling.page import PAGE
from hprior_jax.labelling.store import LabelError, QueryFolder


def make_app(folder: QueryFolder, token: str | None = None):
    """-> the FastAPI app serving `folder`."""
    from fastapi import FastAPI, Request
    from fastapi.exceptions import RequestValidationError
    from fastapi.responses import FileResponse, HTMLResponse, JSONResponse
    from pydantic import BaseModel
    from starlette.exceptions import HTTPException as StarletteHTTPException

    class Answer(BaseModel):
        id: str
        answer: str
        labeller: str

    class Undo(BaseModel):
        labeller: str

    app = FastAPI(title="hprior label", docs_url=None, redoc_url=None, openapi_url=None)

    @app.middleware("http")
    async def require_token(request: Request, call_next):
        if token is not None:
            given = (request.query_params.get("token")
                     or request.headers.get("x-hprior-token") or "")
            if not secrets.compare_digest(given, token):
                return JSONResponse({"error": "this server needs its access token: open the "
                                              "address `hprior label` printed"}, status_code=403)
        return await call_next(request)

    @app.exception_handler(LabelError)
    async def label_error(request: Request, e: LabelError):
        return JSONResponse({"error": str(e)}, status_code=e.status)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, e: StarletteHTTPException):
        what = "no such page or API" if e.status_code == 404 else e.detail
        return JSONResponse({"error": f"{what}: {request.url.path}"}, status_code=e.status_code)

    @app.exception_handler(RequestValidationError)
    async def bad_body(request: Request, e: RequestValidationError):
        problems = "; ".join(dict.fromkeys(_problem(err) for err in e.errors()))
        send = BODIES.get(request.url.path)
        return JSONResponse({"error": f"malformed request: {problems}"
                                      + (f"; send {send}" if send else "")}, status_code=400)

    @app.get("/", response_class=HTMLResponse)
    def page():
        return PAGE

    @app.get("/api/next")
    def next_query():
        q = folder.next_query()
        return {"query": None if q is None else {"id": q.id, "round": q.round, "task": q.task,
                                                 "goal": goal(q.task), "fps": q.fps},
                "progress": folder.progress(None if q is None else q.round)}

    @app.get("/api/clip/{qid}/{side}")
    def clip(qid: str, side: int):
        if side not in (1, 2):
            raise LabelError(f"side {side}: a query has segments 1 and 2")
        return FileResponse(clip_path(folder, qid, side), media_type="video/mp4")

    @app.post("/api/answer")
    def answer(body: Answer):
        written = folder.answer(body.id, body.answer, body.labeller)
        return {"saved": True, "written": written,
                "progress": folder.progress(folder.query(body.id).round)}

    @app.post("/api/undo")
    def undo(body: Undo):
        qid = folder.undo_last(body.labeller)
        return {"undone": qid, "progress": folder.progress()}

    return app


# what each POST takes, as its malformed-request message says
BODIES = {"/api/answer": 'a JSON object {"id": "r1-q0000", "answer": "left" (or right, equal, '
                         'skip), "labeller": "your name"}',
          "/api/undo": 'a JSON object {"labeller": "your name"}'}


def _problem(err: dict) -> str:
    """One of pydantic's validation errors in words (its `loc` is ("body", field...))."""
    where = ".".join(map(str, err["loc"][1:]))
    if err["type"] == "json_invalid":  # loc: the offset where parsing failed
        at = err["loc"][-1] if isinstance(err["loc"][-1], int) else None
        return "the body is not JSON" + (f" (at character {at + 1})" if at is not None else "")
    if err["type"] == "missing":
        return f"the field {where!r} is missing" if where else "the body is missing"
    return (f"the field {where!r}: {err['msg'].lower()}" if where
            else "the body is not a JSON object")

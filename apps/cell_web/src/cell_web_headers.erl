%% @doc A cowboy middleware giving every answer of the panel the headers a browser
%% needs to keep it safe: nothing loaded or run from elsewhere, no framing by other
%% sites, no guessing of content types, no referrer leaving the cell.
-module(cell_web_headers).
-behaviour(cowboy_middleware).

-export([execute/2, headers/0]).

-spec execute(cowboy_req:req(), cowboy_middleware:env()) -> {ok, cowboy_req:req(), cowboy_middleware:env()}.
execute(Req, Env) ->
    {ok, cowboy_req:set_resp_headers(headers(), Req), Env}.

%% @doc The headers set on every answer.
-spec headers() -> #{binary() => binary()}.
headers() ->
    #{<<"content-security-policy">> =>
          <<"default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' data:; "
            "connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'">>,
      <<"x-content-type-options">> => <<"nosniff">>,
      <<"x-frame-options">> => <<"DENY">>,
      <<"referrer-policy">> => <<"no-referrer">>}.

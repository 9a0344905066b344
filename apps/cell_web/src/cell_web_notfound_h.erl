%% @doc Every path the panel does not serve: 404, as JSON like every other error.
-module(cell_web_notfound_h).
-behaviour(cowboy_handler).

-export([init/2]).

-spec init(cowboy_req:req(), map()) -> {ok, cowboy_req:req(), map()}.
init(Req, Opts) ->
    {ok, cell_web_req:reply_error(404, not_found,
                                  <<"there is nothing at ", (cowboy_req:path(Req))/binary>>,
                                  #{}, Req), Opts}.

%% @doc The requests of an ADS connection ({@link cell_hal_ads_client}) in groups
%% ("jobs"), each answered in one piece: queued, in flight under their invoke ids,
%% answered, timed out. Pure: the connection sends what {@link next/1} hands it, as
%% long as it has a free slot, and calls a job's continuation when this module says
%% the job is done.
%%
%% Invoke ids are odd: the even ones are the direct reads' ({@link cell_hal_ads_direct}).
%% One deadline timer serves every job: it is armed for the earliest deadline
%% ({@link arm/2}) and left armed when a job ends early, so a round trip costs no timer
%% operation.
-module(cell_hal_ads_jobs).

-export([new/0, add/6, waiting/1, next/1, answered/3, deliver/4, in_flight/1, arm/2,
         fired/1, due/2, earliest/1, time_out/3, abandon/1]).

-export_type([jobs/0, cont/0]).

-type u32() :: 0..16#FFFFFFFF.
-type answer() :: cell_hal_ads_batch:answer().
%% What the connection does with a job's answers: a function of them and its data.
-type cont() :: fun(([answer()], term()) -> term()).
-type from() :: gen_statem:from() | undefined.

-record(job, {from :: from(),
              deadline :: integer() | infinity,   % monotonic ms
              n :: pos_integer(),
              left :: non_neg_integer(),
              answers = #{} :: #{pos_integer() => answer()},
              received :: non_neg_integer(),   % packets received when it started
              cont :: cont()}).

-record(jobs, {invoke = 0 :: u32(),
               inflight = #{} :: #{u32() => {pos_integer(), pos_integer(),
                                             cell_hal_ads_codec:command()}},
               waiting = queue:new() :: queue:queue({pos_integer(), pos_integer(),
                                                     cell_hal_ads_codec:request()}),
               jobs = #{} :: #{pos_integer() => #job{}},
               seq = 0 :: non_neg_integer(),
               timer_at = infinity :: integer() | infinity}).

-opaque jobs() :: #jobs{}.

%% @doc Nothing queued or in flight.
-spec new() -> jobs().
new() ->
    #jobs{}.

%% @doc A job of requests (at least one) queued, answered to `Cont' when every one is
%% answered or `Deadline' passed; `Received' counts the packets the connection has
%% received so far (a job that times out with none received since says the PLC is
%% gone).
-spec add([cell_hal_ads_codec:request(), ...], from(), integer() | infinity, cont(),
          non_neg_integer(), jobs()) -> jobs().
add(Requests, From, Deadline, Cont, Received, #jobs{seq = Seq, jobs = Jobs, waiting = W} = T) ->
    Id = Seq + 1,
    N = length(Requests),
    Job = #job{from = From, deadline = Deadline, n = N, left = N, received = Received,
               cont = Cont},
    T#jobs{seq = Id, jobs = Jobs#{Id => Job}, waiting = enqueue(Requests, Id, 1, W)}.

enqueue([], _, _, Q) -> Q;
enqueue([R | Rs], Id, I, Q) -> enqueue(Rs, Id, I + 1, queue:in({Id, I, R}, Q)).

%% @doc Whether a request waits to be sent.
-spec waiting(jobs()) -> boolean().
waiting(#jobs{waiting = W}) ->
    not queue:is_empty(W).

%% @doc The next request to send, with the invoke id it goes under (the caller checked
%% that one waits).
-spec next(jobs()) -> {u32(), cell_hal_ads_codec:request(), jobs()}.
next(#jobs{invoke = Last, inflight = In, waiting = W} = T) ->
    {{value, {Id, I, Request}}, W1} = queue:out(W),
    Invoke = next_invoke(Last, In),
    Cmd = cell_hal_ads_codec:request_command(Request),
    {Invoke, Request, T#jobs{invoke = Invoke, inflight = In#{Invoke => {Id, I, Cmd}},
                             waiting = W1}}.

next_invoke(Last, In) ->
    Next = ((Last + 2) band 16#FFFFFFFF) bor 1,
    case maps:is_key(Next, In) of
        true -> next_invoke(Next, In);
        false -> Next
    end.

%% @doc An answer of command `Cmd' under `Invoke': which request of which job it
%% answers (its slot is free now), `{unexpected, Expected}' if that request was of
%% another command, `unknown' if none is in flight under that id.
-spec answered(u32(), cell_hal_ads_codec:command(), jobs()) ->
          {ok, pos_integer(), pos_integer(), jobs()}
        | {unexpected, cell_hal_ads_codec:command()} | unknown.
answered(Invoke, Cmd, #jobs{inflight = In} = T) ->
    case maps:take(Invoke, In) of
        {{Id, I, Cmd}, In1} -> {ok, Id, I, T#jobs{inflight = In1}};
        {{_, _, Expected}, _} -> {unexpected, Expected};
        error -> unknown
    end.

%% @doc Request `I' of job `Id' answered: with its last answer the job is done, and its
%% continuation gets every answer in order.
-spec deliver(pos_integer(), pos_integer(), answer(), jobs()) ->
          {done, cont(), [answer()], jobs()} | {pending, jobs()}.
deliver(Id, I, Answer, #jobs{jobs = Jobs} = T) ->
    case maps:find(Id, Jobs) of
        {ok, #job{left = 1} = Job} ->
            Done = Job#job{answers = (Job#job.answers)#{I => Answer}},
            {done, Job#job.cont, answers(Done), T#jobs{jobs = maps:remove(Id, Jobs)}};
        {ok, #job{left = Left, answers = As} = Job} ->
            Job1 = Job#job{left = Left - 1, answers = As#{I => Answer}},
            {pending, T#jobs{jobs = Jobs#{Id := Job1}}};
        error ->
            {pending, T}
    end.

%% Every answer in order, a timeout for those missing.
answers(#job{n = N, answers = As}) ->
    [maps:get(I, As, {error, timeout}) || I <- lists:seq(1, N)].

%% @doc How many requests are in flight.
-spec in_flight(jobs()) -> non_neg_integer().
in_flight(#jobs{inflight = In}) ->
    map_size(In).

%% @doc The deadline timer fires no later than `Deadline': `set' if it must be set
%% (again) for it.
-spec arm(integer() | infinity, jobs()) -> keep | {set, jobs()}.
arm(Deadline, #jobs{timer_at = At}) when At =< Deadline ->
    keep;
arm(Deadline, T) ->
    {set, T#jobs{timer_at = Deadline}}.

%% @doc The deadline timer fired (or was cancelled).
-spec fired(jobs()) -> jobs().
fired(T) ->
    T#jobs{timer_at = infinity}.

%% @doc The jobs whose deadline has passed at `Now', earliest first.
-spec due(integer(), jobs()) -> [pos_integer()].
due(Now, #jobs{jobs = Jobs}) ->
    [Id || {_, Id} <- lists:sort([{Dl, Id} || {Id, #job{deadline = Dl}} <- maps:to_list(Jobs),
                                             Dl =/= infinity, Dl =< Now])].

%% @doc The earliest deadline of the jobs left.
-spec earliest(jobs()) -> integer() | infinity.
earliest(#jobs{jobs = Jobs}) ->
    lists:min([infinity | [Dl || #job{deadline = Dl} <- maps:values(Jobs), Dl =/= infinity]]).

%% @doc Job `Id' ends at its deadline: its continuation gets what was answered and a
%% timeout for the rest; `Freed' slots are free again; `Dead' if nothing at all was
%% received since it started. `none' if it ended already.
-spec time_out(pos_integer(), non_neg_integer(), jobs()) ->
          {cont(), [answer()], Freed :: non_neg_integer(), Dead :: boolean(), jobs()} | none.
time_out(Id, Received, #jobs{jobs = Jobs, inflight = In, waiting = W} = T) ->
    case maps:take(Id, Jobs) of
        {Job, Jobs1} ->
            In1 = maps:filter(fun(_, {J, _, _}) -> J =/= Id end, In),
            W1 = queue:filter(fun({J, _, _}) -> J =/= Id end, W),
            {Job#job.cont, answers(Job), map_size(In) - map_size(In1),
             Received =:= Job#job.received, T#jobs{jobs = Jobs1, inflight = In1, waiting = W1}};
        error ->
            none
    end.

%% @doc The connection is lost: every job ends unanswered; the callers that wait are
%% returned to be told.
-spec abandon(jobs()) -> {[gen_statem:from()], jobs()}.
abandon(#jobs{jobs = Jobs} = T) ->
    {[From || #job{from = From} <- maps:values(Jobs), From =/= undefined],
     T#jobs{inflight = #{}, waiting = queue:new(), jobs = #{}, timer_at = infinity}}.

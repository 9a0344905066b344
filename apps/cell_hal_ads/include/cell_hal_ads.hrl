%% ADS constants shared by the codec, the client and the tests (Beckhoff TwinCAT ADS).

%% The AMS/TCP port of a TwinCAT router.
-define(ADS_TCP_PORT, 48898).

%% Index groups of the PLC's symbol services.
-define(IG_SYM_HNDBYNAME, 16#F003).     %% ReadWrite: name -> handle
-define(IG_SYM_VALBYHND, 16#F005).      %% Read/Write by handle (offset = handle)
-define(IG_SYM_RELEASEHND, 16#F006).    %% Write: release a handle
-define(IG_SYM_VERSION, 16#F008).       %% Read 1 byte: the symbol version
-define(IG_SYM_INFOBYNAMEEX, 16#F009).  %% ReadWrite: name -> symbol entry
-define(IG_SYM_UPLOAD, 16#F00B).        %% Read: the symbol table
-define(IG_SYM_UPLOADINFO, 16#F00C).    %% Read 8 bytes: symbol count and table size

%% Sum commands: several sub-commands in one ReadWrite (offset = sub-command count).
-define(IG_SUMUP_READ, 16#F080).
-define(IG_SUMUP_WRITE, 16#F081).
-define(IG_SUMUP_READWRITE, 16#F082).

%% ADS data type ids of symbol entries.
-define(ADST_INT16, 2).
-define(ADST_INT32, 3).
-define(ADST_REAL32, 4).
-define(ADST_REAL64, 5).
-define(ADST_INT8, 16).
-define(ADST_UINT8, 17).
-define(ADST_UINT16, 18).
-define(ADST_UINT32, 19).
-define(ADST_INT64, 20).
-define(ADST_UINT64, 21).
-define(ADST_STRING, 30).
-define(ADST_WSTRING, 31).
-define(ADST_BIT, 33).
-define(ADST_BIGTYPE, 65).

%% Errors after which a client's handle may belong to an older program.
-define(STALE_HANDLE_ERRORS, [16#710, 16#711, 16#714, 16#722]).

%% Symbol entry flags.
-define(SYMFLAG_BITVALUE, 16#2).

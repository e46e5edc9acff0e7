MODULE EyetohandCollect
    ! eyetohand calibration collection for ABB robots (RAPID, IRC5 / OmniCore, option PC Interface
    ! or Socket Messaging). UNTESTED: no ABB controller here. Read examples/robots/README.md first.
    !
    ! Vision side: eyetohand serve --tcp 0.0.0.0:5000 --camera URI
    !
    ! Traps handled here:
    ! * A RAPID string holds at most 80 characters. SocketReceive \Str takes at most 80 bytes and
    !   leaves the rest of a longer reply in the socket, where it would be read as the NEXT reply:
    !   ReadLine below reads byte by byte up to LF, keeps the first 80 characters and drops the rest.
    ! * Replies end with LF (a CR before it is dropped); commands are sent with CR LF.
    ! * SocketReceive waits 60 s by default and then raises ERR_SOCK_TIMEOUT: \Time:=30 here, and the
    !   ERROR handler turns a timeout into a stop with a message instead of a hanging program.
    ! * NumToStr gives a "." decimal point whatever the FlexPendant's language.
    ! * MoveL ... fine: the robot stops exactly on the point before the POINT command (a zone would
    !   let the program run ahead while the robot is still moving).

    CONST string HOST := "192.168.125.10";   ! the vision PC
    CONST num PORT := 5000;
    CONST string BEGIN_CMD := "CAL BEGIN cell1,grid:5x5,-40,570,60,650,150";
    CONST num TIMEOUT_S := 30;
    PERS tooldata tCalTarget := [TRUE, [[0, 0, 120], [1, 0, 0, 0]], [0.5, [0, 0, 50], [1, 0, 0, 0], 0, 0, 0]];
    PERS wobjdata wCal := [FALSE, TRUE, "", [[0, 0, 0], [1, 0, 0, 0]], [[0, 0, 0], [1, 0, 0, 0]]];

    VAR socketdev sock;
    VAR string reply;
    VAR num vals{3};
    VAR num nvals;

    PROC main()
        VAR robtarget p;
        VAR string cmd;
        SocketClose sock;
        SocketCreate sock;
        SocketConnect sock, HOST, PORT \Time:=10;
        IF NOT Command(BEGIN_CMD) StopCal(reply);
        p := CRobT(\Tool:=tCalTarget \WObj:=wCal);
        WHILE TRUE DO
            IF NOT Command("CAL NEXT") StopCal(reply);
            IF reply = "OK DONE" GOTO done;
            IF nvals <> 3 StopCal("CAL NEXT: expected x,y,z in " + reply);
            p.trans := [vals{1}, vals{2}, vals{3}];
            MoveL p, v100, fine, tCalTarget \WObj:=wCal;
            WaitTime 0.5;
            cmd := "CAL POINT " + NumToStr(vals{1}, 4) + "," + NumToStr(vals{2}, 4) + ","
                   + NumToStr(vals{3}, 4);
            IF NOT Command(cmd) THEN
                IF StrPart(reply, 1, 10) = "ERR moving" THEN
                    WaitTime 1;
                    IF NOT Command(cmd) TPWrite "eyetohand: point skipped: " + reply;
                ELSE
                    TPWrite "eyetohand: point skipped: " + reply;
                ENDIF
            ENDIF
        ENDWHILE
        done:
        IF NOT Command("CAL END") StopCal(reply);
        TPWrite "eyetohand: calibrated: " + reply;
        SocketClose sock;
    ERROR
        IF ERRNO = ERR_SOCK_TIMEOUT THEN
            TPWrite "eyetohand: no answer from the vision PC within the timeout";
        ELSEIF ERRNO = ERR_SOCK_CLOSED THEN
            TPWrite "eyetohand: the vision PC closed the connection";
        ENDIF
        SocketClose sock;
        Stop;
    ENDPROC

    PROC StopCal(string why)
        TPWrite "eyetohand: stopped: " + StrPart(why, 1, Min(StrLen(why), 60));
        SocketClose sock;
        Stop;
    ENDPROC

    ! Send one command (CR LF), read the reply; TRUE when it starts with OK. The numbers after
    ! "OK " go to vals{1..3} (nvals of them).
    FUNC bool Command(string cmd)
        SocketSend sock \Str:=cmd + "\0D\0A";
        reply := ReadLine();
        nvals := 0;
        IF StrPart(reply, 1, 2) <> "OK" RETURN FALSE;
        IF StrLen(reply) > 3 AND reply <> "OK DONE" ParseNumbers StrPart(reply, 4, StrLen(reply) - 3);
        RETURN TRUE;
    ENDFUNC

    FUNC string ReadLine()
        VAR string line := "";
        VAR string ch;
        WHILE TRUE DO
            SocketReceive sock \Str:=ch \ReadNoOfBytes:=1 \Time:=TIMEOUT_S;
            IF ch = "\0A" RETURN line;
            IF ch <> "\0D" AND StrLen(line) < 80 line := line + ch;
        ENDWHILE
    ENDFUNC

    PROC ParseNumbers(string text)
        VAR num start := 1;
        VAR num comma;
        VAR bool ok;
        WHILE start <= StrLen(text) AND nvals < 3 DO
            comma := StrFind(text, start, ",");
            Incr nvals;
            ok := StrToVal(StrPart(text, start, comma - start), vals{nvals});
            IF NOT ok StopCal("not a number in " + text);
            start := comma + 1;
        ENDWHILE
    ENDPROC
ENDMODULE
